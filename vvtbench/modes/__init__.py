"""Image-space mode identification: streamed spectra, peaks, sampling at mesh vertices."""
