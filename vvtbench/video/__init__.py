"""Video files in and out: lossless writing, probing, streamed reading, camera formats.

* :mod:`vvtbench.video.frames`: what every reader shares (:class:`VideoError`, gray frames).
* :mod:`vvtbench.video.cameras`: one reader per high-speed camera format (Photron
  .cih/.cihx + .mraw, Phantom .cine, image sequences, .npy).
* :mod:`vvtbench.video.files`: probe, read and write ordinary video files, and
  :func:`~vvtbench.video.files.open_video`, which opens either kind.
"""

from .._aliases import forward

#: ``from vvtbench.video import NAME`` (the module before it became this package) still works,
#: with a DeprecationWarning naming vvtbench.video.files
__getattr__ = forward("vvtbench.video", "vvtbench.video.files", globals())
