"""The field path: a real camera's files and a real object to a material map.

Camera-file readers (image sequences, Photron, Phantom) behind
:func:`vvtbench.video.files.open_video`,
the object (a surface mesh, a box or plate by size, a scene without its material),
calibration from clicked points, and ``invert``, which composes extract, observe and solve
into a report folder.
"""
