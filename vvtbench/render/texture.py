"""Speckle textures and seam-tolerant texture coordinates for arbitrary surfaces.

Two pieces:

* :func:`speckle_texture` -- a seeded, *tileable* (periodic) random speckle
  pattern as a ``float32`` image in ``[0, 1]``, the kind of pattern painted on
  specimens for digital image correlation.
* :func:`triplanar_mapping` -- per-vertex texture coordinates for any triangle
  surface.  Every face is projected onto the coordinate plane most
  perpendicular to its normal (its "dominant axis"), so no face is stretched by
  more than ``sqrt(3)`` in any direction and no face is degenerate in texture
  space.  Vertices are duplicated where faces of different dominant axes meet;
  :attr:`TexturedMesh.source_index` maps every render vertex back to the
  original vertex so per-frame displacements can be applied.

Texture coordinates are ``world_coordinate / tile_size``; the texture must be
sampled with wrap mode REPEAT, which is seamless because the speckle image is
periodic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["TexturedMesh", "speckle_texture", "triplanar_mapping"]


def speckle_texture(
    size: int = 1024,
    *,
    grain: float = 4.0,
    density: float = 0.5,
    contrast: float = 1.0,
    seed: int = 0,
    dark_speckles: bool = True,
) -> np.ndarray:
    """Seeded periodic random speckle pattern.

    Speckles are Gaussian blobs of standard deviation ``grain`` texels placed
    uniformly at random (a Poisson process) and summed; the pattern wraps
    around both edges, so it can be tiled without seams.

    Parameters
    ----------
    size : int
        Side length of the square image in texels (a power of two is best for
        mipmapping, but not required).
    grain : float
        Speckle radius: the Gaussian standard deviation in texels (> 0).
    density : float
        In ``(0, 1)``: approximate fraction of the area covered by speckles
        (darker than mid-grey for dark speckles).  ``0.5`` gives a balanced
        pattern.
    contrast : float
        In ``(0, 1]``: the pattern spans ``[0.5 - contrast/2, 0.5 + contrast/2]``.
    seed : int
        Seed of :func:`numpy.random.default_rng`; equal arguments give
        bit-identical images.
    dark_speckles : bool
        Dark speckles on a bright background (default) or the opposite.

    Returns
    -------
    ndarray, shape (size, size), float32
        Values in ``[0, 1]``.

    Examples
    --------
    >>> tex = speckle_texture(64, grain=2.0, seed=1)
    >>> tex.shape, tex.dtype, bool(tex.min() >= 0.0), bool(tex.max() <= 1.0)
    ((64, 64), dtype('float32'), True, True)
    >>> bool(np.array_equal(tex, speckle_texture(64, grain=2.0, seed=1)))
    True
    """
    size = int(size)
    if size < 4:
        raise ValueError("size must be >= 4")
    if not grain > 0:
        raise ValueError("grain must be positive")
    if not 0 < density < 1:
        raise ValueError("density must be in (0, 1)")
    if not 0 < contrast <= 1:
        raise ValueError("contrast must be in (0, 1]")
    rng = np.random.default_rng(seed)
    # Poisson coverage 1 - exp(-lambda * A) with an effective blob area
    # A ~ 7 grain^2 (calibrated for the saturating map below).
    n_expected = -np.log1p(-density) * size * size / (7.0 * grain**2)
    n = max(int(rng.poisson(n_expected)), 1)
    # Impulses at sub-texel positions via bilinear splatting, then a periodic
    # Gaussian blur in the Fourier domain: smooth, band-limited and tileable.
    pos = rng.uniform(0.0, size, size=(n, 2))
    amp = rng.uniform(0.7, 1.0, size=n)
    i0 = np.floor(pos).astype(np.int64)
    f = pos - i0
    img = np.zeros((size, size), dtype=np.float64)
    for di in (0, 1):
        wi = f[:, 0] if di else 1.0 - f[:, 0]
        for dj in (0, 1):
            wj = f[:, 1] if dj else 1.0 - f[:, 1]
            np.add.at(img, ((i0[:, 0] + di) % size, (i0[:, 1] + dj) % size), amp * wi * wj)
    k = np.fft.fftfreq(size)
    k2 = k[:, None] ** 2 + k[None, :] ** 2
    # splatting is a tent filter; the Gaussian dominates for grain >~ 1
    img = np.fft.ifft2(np.fft.fft2(img) * np.exp(-2.0 * (np.pi * grain) ** 2 * k2)).real
    # Saturating map so that overlapping speckles do not dominate the range.
    peak = 1.0 / (2.0 * np.pi * grain**2)
    img = 1.0 - np.exp(-img / (0.5 * peak))
    lo, hi = float(img.min()), float(img.max())
    img = (img - lo) / (hi - lo) if hi > lo else np.zeros_like(img)
    if dark_speckles:
        img = 1.0 - img
    img = 0.5 + contrast * (img - 0.5)
    return np.clip(img, 0.0, 1.0).astype(np.float32)


@dataclass(frozen=True, eq=False)
class TexturedMesh:
    """Triangle surface prepared for texturing.

    Attributes
    ----------
    vertices : ndarray, shape (M, 3)
        Render vertices (copies of original vertices).
    triangles : ndarray, shape (F, 3)
        Faces indexing ``vertices``; face ``f`` is original face ``f``.
    uv : ndarray, shape (M, 2)
        Texture coordinates (in tiles; sample with REPEAT).
    source_index : ndarray, shape (M,)
        Original vertex index of every render vertex.
    face_axis : ndarray, shape (F,)
        Dominant axis (0, 1, 2) used to texture each face.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    uv: np.ndarray
    source_index: np.ndarray
    face_axis: np.ndarray

    def expand(self, values: np.ndarray) -> np.ndarray:
        """Per-original-vertex values ``(N, ...)`` to per-render-vertex ``(M, ...)``."""
        return np.asarray(values)[self.source_index]


def triplanar_mapping(
    vertices: np.ndarray, triangles: np.ndarray, tile_size: float
) -> TexturedMesh:
    """Triplanar texture coordinates, one projection plane per face.

    Each face is assigned the axis ``a = argmax |n_a|`` of its normal and its
    vertices get ``uv = (X_b, X_c) / tile_size`` with ``(b, c)`` the two other
    axes (``b < c``).  Original vertices used by faces of several axes are
    duplicated, once per axis.  The mapping is a function of the *rest*
    positions only: displaced vertices keep their uv, i.e. the texture is
    painted on the material.

    Parameters
    ----------
    vertices : array_like, shape (N, 3)
    triangles : array_like, shape (F, 3), int
    tile_size : float
        World length covered by one repetition of the texture image.

    Returns
    -------
    TexturedMesh

    Examples
    --------
    >>> import numpy as np
    >>> v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    >>> f = np.array([[0, 2, 1], [0, 1, 3]])   # one face in z=0, one in y=0
    >>> m = triplanar_mapping(v, f, tile_size=2.0)
    >>> m.face_axis.tolist(), m.source_index.tolist()
    ([2, 1], [0, 0, 1, 1, 2, 3])
    >>> m.uv[m.triangles[1]].tolist()   # (x, z) / 2 for the y-face
    [[0.0, 0.0], [0.5, 0.0], [0.0, 0.5]]
    """
    V = np.asarray(vertices, dtype=np.float64)
    Fc = np.asarray(triangles)
    if V.ndim != 2 or V.shape[1] != 3:
        raise ValueError("vertices must have shape (N, 3)")
    if Fc.ndim != 2 or Fc.shape[1] != 3 or not np.issubdtype(Fc.dtype, np.integer):
        raise ValueError("triangles must be an integer array of shape (F, 3)")
    if Fc.size and (Fc.min() < 0 or Fc.max() >= len(V)):
        raise ValueError("triangle index out of range")
    if not tile_size > 0:
        raise ValueError("tile_size must be positive")
    F = Fc.astype(np.int64)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    axis = np.argmax(np.abs(n), axis=1)
    # One render vertex per (original vertex, axis) pair actually used.
    key = F * 3 + axis[:, None]
    uniq, inverse = np.unique(key.ravel(), return_inverse=True)
    src = uniq // 3
    ax = uniq % 3
    other = np.array([[1, 2], [0, 2], [0, 1]])[ax]
    rv = V[src]
    uv = np.take_along_axis(rv, other, axis=1) / tile_size
    return TexturedMesh(
        vertices=rv,
        triangles=inverse.reshape(F.shape).astype(np.int64),
        uv=uv,
        source_index=src,
        face_axis=axis,
    )
