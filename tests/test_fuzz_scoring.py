"""Properties of the extraction scoring (docs/modes.md, "Matching") on random truth and
detections: one-to-one, never above the counts, every pair inside its window and above the
MAC floor, and the truth itself scored perfect."""

from __future__ import annotations

import numpy as np
import pytest

from vvtbench.scoring.extraction import score_extraction, subspace_mac

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from test_modes import modeset  # noqa: E402

N = 6  # shapes are (N, N, 2)


@st.composite
def cases(draw):
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    n = draw(st.integers(1, 7))
    # frequencies often closer than the resolution (0.5 Hz): chained clusters
    f_true = np.sort(1.0 + np.cumsum(rng.choice([0.1, 0.3, 0.6, 1.5], size=n)))
    truth = rng.standard_normal((n, N, N, 2))
    k = draw(st.integers(0, 9))
    src = rng.integers(0, n, size=k)
    mix = draw(st.floats(0.0, 2.0))
    shapes = truth[src] + mix * rng.standard_normal((k, N, N, 2))
    f_det = f_true[src] + rng.uniform(-0.8, 0.8, size=k)
    return f_true, truth, f_det, shapes


@settings(max_examples=150, deadline=None, derandomize=True)
@given(cases())
def test_matching_is_one_to_one_and_inside_its_windows(case):
    f_true, truth, f_det, shapes = case
    det = modeset(f_det, shapes.astype(np.float32).reshape(len(f_det), N, N, 2))
    r = score_extraction(det, f_true, None, truth, duration_s=2.0, fmax=50.0)
    df = r["frequency_resolution_hz"]
    assert 0 <= r["n_matched"] <= min(r["n_detected"], r["n_true_in_band"])
    detected = [m["detected"] for m in r["matching"]]
    assert len(set(detected)) == len(detected)
    resolved = [m["nearest_true"] for m in r["matching"] if m["kind"] == "mode"]
    assert len(set(resolved)) == len(resolved)
    clusters = [m["true"] for m in r["matching"] if m["kind"] == "cluster"]
    assert len({tuple(c) for c in clusters}) == len(clusters)
    for c in clusters:  # a cluster is matched as a whole only when no mode of it was
        assert not set(c) & set(resolved)
    for m in r["matching"]:
        assert m["mac"] >= r["min_mac"] - 1e-12
        ft = f_true[m["true"]]
        if m["kind"] == "mode":
            assert abs(m["frequency_hz"] - m["true_frequency_hz"]) <= df + 1e-12
            own = subspace_mac(shapes[m["detected"]].ravel(),
                               truth[[m["nearest_true"]]].reshape(1, -1))
            assert own >= r["min_mac"] - 1e-12
        else:
            assert ft.min() - df - 1e-12 <= m["frequency_hz"] <= ft.max() + df + 1e-12
    assert len(r["unmatched"]) == r["n_detected"] - r["n_matched"]
    # the truth itself, at its own frequencies: every mode resolved, nothing false
    exact = modeset(f_true, truth.astype(np.float32))
    p = score_extraction(exact, f_true, None, truth, duration_s=2.0, fmax=50.0)
    assert p["precision"] == 1.0 and p["recall"] == 1.0 and p["recall_modes"] == 1.0
    assert {m["kind"] for m in p["matching"]} == {"mode"}
