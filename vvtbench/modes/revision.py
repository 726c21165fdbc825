"""Revisions of the mode extraction: part of the cache keys of everything built on it.

A stored extraction (a run's cache, the modes kept beside a sample for learners) is reused only
under the revision that made it; bump a number when the extraction's output or its meaning
changes, and say why here and in CHANGELOG.md ("Cache revisions").
"""

from __future__ import annotations

__all__ = ["EXTRACTION_REVISION", "LINE_FIT_REVISION", "POLE_REVISION", "extraction_revision"]

#: revision of the mode extraction and of its scoring (part of the extract and observe keys
#: of extracted tracks only: true-mode tracks keep their cache). 2: shoulder modes, recall
#: over the modes detectable in the video; 3: library defaults chosen on validation videos
#: (noise weights for the peaks, faint products rejected, no cap), products folded at Nyquist;
#: 4: faint products measured against ``P_i P_j / P_max`` (``product_scaling``); 5: camera-shake
#: peaks are parents of distortion products (a pure-shake video has no modes); 6: peak-picked
#: dampings' intervals span the fit without window too; 7: the damping fit's log-power polish
#: with its analytic Jacobian, at most ``POLISH_EVALUATIONS`` evaluations; 8: motion against
#: the temporal mean of the record (not its first frame), the phase refined about its
#: estimate, the identifier (peak picker, ERA, pLSCF; ``identifier``, ``auto`` choosing from
#: the excitation or the envelope) recorded in every mode set, and the opt-in product test's
#: harmonics to the 7th
EXTRACTION_REVISION = 8
#: revision of the opt-in line fit (``[extract] line_fit = true``; only its keys change).
#: 2: lines the residual search added are dropped when rough (``added_roughness``); 3: lines
#: up to ``2 radius`` bins wide (the 3-bin bound clipped the damping of heavily damped modes)
LINE_FIT_REVISION = 3
#: revision of the pole-based identifiers (``[extract] identifier`` other than ``"peaks"``;
#: only their keys change). 1: ERA / pLSCF over block-averaged channels, stabilisation and
#: clustering, shapes by projection, products by frequency, decay, phase and shape
POLE_REVISION = 1


def extraction_revision(extract_opts: dict) -> int | list[int | str]:
    """The revision part of the extract and observe keys of extracted tracks."""
    out = [EXTRACTION_REVISION]
    if extract_opts.get("line_fit"):
        out.append(LINE_FIT_REVISION)
    if extract_opts.get("identifier", "peaks") != "peaks":
        out.append(f"p{POLE_REVISION}")
    return out if len(out) > 1 else EXTRACTION_REVISION
