"""What the measured motion holds besides the true modes: the extractor's residual and its
products, measured against the truth's image modes.

For a sample folder (video and truth): the phase extractor's displacements are averaged over
8×8-pixel tiles with the noise weights (the channels the pole-based identifiers read,
:func:`vvtbench.modes.reduce.block_channels`); the truth's modal coordinates ``q_i(t)`` (the
least-squares fit of the stored surface displacements by the surface modes) are regressed on
every channel, so the fit holds each true mode with whatever gain and shape the extractor gives
it; the residual is what is not linear in the true motion. Printed:

* the RMS of the channels and of the residual, and the residual's energy per frame over five
  stretches of the record (a residual of the motion decays with it, a floor does not);
* the residual's power at the harmonics and sums of the two strongest true modes, before and
  after regressing it on the products ``q_i q_j`` of the strongest coordinates, against the
  linear fit's power at the parents: the amplitude of each product line relative to its
  parents'.

Usage: ``python benchmarks/bench_product_levels.py SAMPLE``.
"""

from __future__ import annotations

import argparse
import itertools

import numpy as np

from vvtbench.modes import DisplacementStore
from vvtbench.modes.extract import confidence_weights, noise_weights
from vvtbench.modes.reduce import block_channels
from vvtbench.modes.spectrum import pixel_noise_power
from vvtbench.samples.reader import open_sample


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sample")
    args = ap.parse_args()
    from bench_identifiers import displacements

    s = open_sample(args.sample)
    with DisplacementStore() as store:
        motion = displacements(s, store)
        cw = confidence_weights(motion.grid_confidence)
        nw = noise_weights(cw, pixel_noise_power(store))
        Y = block_channels(store, weights=nw, block=8).data
    T, fps = Y.shape[0], float(s.fps)
    surf = np.asarray(s["modes/surface"], np.float64)
    n = surf.shape[0]
    u = np.asarray(s["transient/displacements"], np.float64).reshape(T, -1)
    q = u @ np.linalg.pinv(surf.reshape(n, -1).T).T
    Y = Y - Y.mean(0)
    Q = q - q.mean(0)
    f = np.asarray(s.frequencies_hz, np.float64)
    B, *_ = np.linalg.lstsq(Q, Y, rcond=None)
    L = Q @ B
    R = Y - L
    print(f"{s.scene.name}: {T} frames at {fps:g} fps, {Y.shape[1]} channels")
    print(f"RMS of the channels {np.sqrt(Y.var()):.3g} px, of the residual {np.sqrt(R.var()):.3g}"
          f" px ({np.sqrt(R.var() / Y.var()):.1%})")
    e = (R**2).sum(1)
    cuts = np.linspace(0, T, 6).astype(int)
    print("residual energy per frame (px²) over the record:",
          ", ".join(f"{e[a:b].mean():.3g}" for a, b in zip(cuts[:-1], cuts[1:], strict=True)))
    F = np.fft.rfftfreq(T, 1 / fps)
    PL = (np.abs(np.fft.rfft(L, axis=0)) ** 2).sum(1)
    # the modes by the power of the linear fit at their frequency (repeated modes move
    # together: their coefficients one by one are not determined)
    line = PL[np.clip(np.rint(f * T / fps).astype(int), 0, F.size - 1)]
    rank = [int(k) for k in np.argsort(-line)]
    i1 = rank[0]
    i2 = next(k for k in rank if abs(f[k] - f[i1]) > fps / T)
    strong = [i1, i2] + [k for k in rank if k not in (i1, i2)][:1]
    quad = np.stack([Q[:, a] * Q[:, b] for a, b in
                     itertools.combinations_with_replacement(strong, 2)], 1)
    quad -= quad.mean(0)
    C, *_ = np.linalg.lstsq(quad, R, rcond=None)
    R2 = R - quad @ C

    def power(X, f0):
        k = int(round(f0 * T / fps))
        P = (np.abs(np.fft.rfft(X[:, :], axis=0)) ** 2).sum(1)
        return float(P[max(k - 1, 0):k + 2].max())

    f1, f2 = f[i1], f[i2]
    p1, p2 = power(L, f1), power(L, f2)
    print(f"parents: {f1:.3f} Hz and {f2:.3f} Hz")
    print("| line | Hz | residual power | after q_i q_j | product amplitude / parents' |")
    print("|---|---|---|---|---|")
    for name, fr, ref in (("2 f1", 2 * f1, p1), ("2 f2", 2 * f2, p2),
                          ("f1 + f2", f1 + f2, np.sqrt(p1 * p2)),
                          ("|f1 - f2|", abs(f1 - f2), np.sqrt(p1 * p2)),
                          ("3 f1", 3 * f1, p1)):
        a, b = power(R, fr), power(R2, fr)
        print(f"| {name} | {fr:.2f} | {a:.3g} | {b:.3g} | {np.sqrt(max(a - b, 0) / ref):.2%} |")


if __name__ == "__main__":
    main()
