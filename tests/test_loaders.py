"""InstanceDataset: fixed-shape items with masks, the feature spec, worker safety, exported
datasets, and extracted modes computed once."""

from __future__ import annotations

import multiprocessing
import re
from pathlib import Path

import numpy as np
import pytest

from vvtbench.cli import main
from vvtbench.datasets.loaders import FEATURES, InstanceDataset
from vvtbench.samples.reader import DatasetError, check_sample, open_sample
from vvtbench.scene.scene import SCENES_DIR

N_TRAIN, N_MODES = 3, 12


def _family(tmp: Path) -> Path:
    """The shipped cube family, made small: 5^3 cells, 12 modes, 96^2 px, 0.4 s at 400 fps."""
    text = (SCENES_DIR / "families" / "cube_defects.toml").read_text()
    text = text.replace('name = "cube_defects"', 'name = "tinycube"')
    text += ('"simulation.n_modes" = { choice = [12] }\n'
             '"geometry.cells" = { choice = [[5, 5, 5]] }\n'
             '"camera.resolution" = { choice = [[96, 96]] }\n'
             '"simulation.duration" = { choice = [0.4] }\n'
             '"simulation.fps" = { choice = [400.0] }\n')
    path = tmp / "tinycube.toml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("loaders")
    fam = _family(tmp)
    train, video = tmp / "train", tmp / "video"
    assert main(["generate", str(fam), "--split", "train", "--n", str(N_TRAIN), "--no-video",
                 "-o", str(train), "--no-progress"]) == 0
    assert main(["generate", str(fam), "--split", "val", "--n", "1", "-o", str(video),
                 "--no-progress"]) == 0
    return tmp


def _flat(item: dict) -> dict:
    return {f"{part}/{k}": v for part in ("inputs", "targets")
            for k, v in item.get(part, {}).items()}


def test_length_shapes_spec_split_and_id(data):
    ds = InstanceDataset(data / "train", "train", max_modes=16)
    assert len(ds) == N_TRAIN
    assert ds.names == [f"tinycube-train-{i:05d}" for i in range(N_TRAIN)]
    spec = ds.features()
    assert [f.name for f in spec] == [f.name for f in FEATURES]
    shapes = {f.name: f.shape for f in spec}
    assert shapes["gamma"] == (16, 729, 2) and shapes["active"] == (8, 8, 8)
    for i in range(len(ds)):
        item = ds[i]
        assert item["split"] == "train" and item["instance"] == ds.names[i]
        assert item["index"] == i and item["family"] == "tinycube"
        flat = _flat(item)
        assert set(flat) == {f"{f.part}/{f.name}" for f in spec}
        for f in spec:
            value = np.asarray(flat[f"{f.part}/{f.name}"])
            assert value.shape == f.shape, f.name
            assert value.dtype == np.dtype(f.dtype), f.name
    text = ds.describe()
    assert re.search(r"inputs\s+gamma\s+16x729x2\s+float32", text)
    assert re.search(r"targets\s+w\s+8x8x8\s+float32\s+Pa", text)
    with pytest.raises(IndexError):
        ds[N_TRAIN]
    assert ds[-1]["instance"] == ds.names[-1]
    with pytest.raises(DatasetError, match=r"train: no instance of split 'test' \(here: train\)"):
        InstanceDataset(data / "train", "test")
    with pytest.raises(ValueError, match="split"):
        InstanceDataset(data / "train", "training")


def test_missing_modes_and_hidden_vertices_are_masked(data):
    from vvtbench.observe import observe

    ds = InstanceDataset(data / "train", "train", max_modes=16)
    item = ds[1]
    x = item["inputs"]
    assert x["mode_mask"].tolist() == [True] * N_MODES + [False] * (16 - N_MODES)
    assert not x["gamma"][N_MODES:].any() and not x["eigenvalues"][N_MODES:].any()
    assert np.all(np.diff(x["eigenvalues"][:N_MODES]) >= 0)
    # every present mode has unit norm over the visible nodes, nothing at hidden ones
    norms = np.sqrt((x["gamma"][:N_MODES] ** 2).sum(axis=(1, 2)))
    np.testing.assert_allclose(norms, 1.0, rtol=1e-5)
    assert not x["gamma"][:, ~x["visible"]].any()
    assert not x["jacobian"][~x["visible"]].any()

    # hidden by geometry: interior nodes, the fixed base, and faces turned away from the camera
    sample = open_sample(data / "train" / ds.names[1])
    pts = x["points"].astype(float)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    center = -np.asarray(x["camera_R"], float).T @ np.asarray(x["camera_t"], float)
    tol = 1e-6 * (hi - lo).max()
    front = np.zeros(len(pts), bool)
    on_surface = np.zeros(len(pts), bool)
    for axis in range(3):
        for bound, sign in ((lo, -1.0), (hi, 1.0)):
            on_face = np.abs(pts[:, axis] - bound[axis]) < tol
            on_surface |= on_face
            if sign * (center[axis] - bound[axis]) > 0:
                front |= on_face
    assert (~on_surface).sum() == 7 ** 3
    hidden = ~front | x["fixed"]
    assert hidden.sum() > 0 and front.sum() > 0
    assert not x["visible"][hidden].any()
    assert x["visible"].sum() > 10

    # the observed values are those of observe(), at the visible nodes, in its order
    problem, _ = observe(sample, n_modes=N_MODES)
    vis = problem.visible_nodes
    assert set(np.flatnonzero(x["visible"])) == set(vis.tolist())
    np.testing.assert_allclose(x["gamma"][:N_MODES, vis].reshape(N_MODES, -1), problem.gamma,
                               rtol=1e-5, atol=1e-7)
    # the Jacobian is the camera's analytic one at each visible, free node
    cam = sample.camera
    free = ~x["fixed"][vis]
    np.testing.assert_allclose(x["jacobian"][vis[free]], cam.jacobian(pts[vis[free]]),
                               rtol=1e-4, atol=1e-3)


def test_targets_are_apart_and_conserve_the_material(data):
    ds = InstanceDataset(data / "train", "train", max_modes=N_MODES)
    no_truth = InstanceDataset(data / "train", "train", max_modes=N_MODES, targets=False)
    assert all(f.part == "inputs" for f in no_truth.features())
    item, bare = ds[2], no_truth[2]
    assert "targets" not in bare and set(item["targets"]) == {"w", "v"}
    for k, a in bare["inputs"].items():
        np.testing.assert_array_equal(a, item["inputs"][k])
    # equal voxels over equal elements: the voxel means keep the body's mean material
    sample = open_sample(data / "train" / ds.names[2])
    active = item["inputs"]["active"]
    assert active.all()
    for key, name in (("w", "material/stiffness"), ("v", "material/density")):
        per_element = np.asarray(sample[name], float)
        assert item["targets"][key].mean() == pytest.approx(per_element.mean(), rel=1e-5)


def test_exported_datasets_give_the_same_arrays(data):
    folder = InstanceDataset(data / "train", "train", max_modes=16)
    for out in ("pack.zarr", "pack.h5"):
        assert main(["export", str(data / "train"), "-o", str(data / out)]) == 0
        packed = InstanceDataset(data / out, "train", max_modes=16)
        assert packed.names == folder.names
        assert packed.features() == folder.features()
        for i in range(len(folder)):
            a, b = folder[i], packed[i]
            assert {k: a[k] for k in ("split", "instance", "family", "index")} == \
                   {k: b[k] for k in ("split", "instance", "family", "index")}
            fa, fb = _flat(a), _flat(b)
            assert set(fa) == set(fb)
            for k in fa:
                np.testing.assert_array_equal(fa[k], fb[k], err_msg=f"{out} {k}")
        packed.close()


def _items(ds, indices):
    return [ds[i] for i in indices]


@pytest.mark.parametrize("source", ["train", "pack.h5"])
def test_forked_workers_read_the_same_items(data, source):
    """A DataLoader with workers: the dataset forked into a pool, each worker reading items
    (an HDF5 handle opened in the parent is never used by a child)."""
    if source == "pack.h5" and not (data / source).exists():
        assert main(["export", str(data / "train"), "-o", str(data / source)]) == 0
    ds = InstanceDataset(data / source, "train", max_modes=16)
    here = _items(ds, range(len(ds)))  # opens this process's handle first
    ctx = multiprocessing.get_context("fork")
    with ctx.Pool(2) as pool:
        there = pool.starmap(_items, [(ds, [i]) for i in range(len(ds))] * 2)
    for k, (got,) in enumerate(there):
        want = here[k % len(ds)]
        assert got["instance"] == want["instance"]
        for name, value in _flat(want).items():
            np.testing.assert_array_equal(_flat(got)[name], value)


def test_extracted_modes_are_computed_once(data, monkeypatch):
    import vvtbench.modes
    from vvtbench.datasets.instances import iter_instances

    calls = []
    real = vvtbench.modes.extract_modes

    def counting(*args, **kwargs):
        calls.append(args[0])
        return real(*args, **kwargs)

    monkeypatch.setattr(vvtbench.modes, "extract_modes", counting)
    ds = InstanceDataset(data / "video", "val", observation="extracted", max_modes=8)
    first = ds[0]
    assert len(calls) == 1
    second = ds[0]  # the next epoch
    again = InstanceDataset(data / "video", "val", observation="extracted", max_modes=8)[0]
    assert len(calls) == 1
    for item in (second, again):
        for k, v in _flat(first).items():
            np.testing.assert_array_equal(_flat(item)[k], v)
    x = first["inputs"]
    n = int(x["mode_mask"].sum())
    assert 1 <= n <= 8 and x["mode_mask"][:n].all() and not x["eigenvalues"][n:].any()
    for _ in range(2):
        pairs = list(iter_instances(data / "video", "val", observation="extracted",
                                    n_modes=8))
    assert len(calls) == 1 and pairs[0][0].n_modes == n
    assert main(["export", str(data / "video"), "-o", str(data / "video.zarr")]) == 0
    for _ in range(2):  # from the packed video's frames, once
        packed = InstanceDataset(data / "video.zarr", "val", observation="extracted",
                                 max_modes=8)[0]
        assert len(calls) == 2
        for k, v in _flat(first).items():
            np.testing.assert_array_equal(_flat(packed)[k], v)

    cached = data / "video" / ".vvtbench-extracted" / ds.names[0]
    (folder,) = cached.iterdir()
    assert folder.name.startswith("phase-r")
    sample = data / "video" / ds.names[0]
    assert check_sample(sample, open_sample(sample).manifest, open_sample(sample).info,
                        full=True) == []  # nothing was written into the sample
    npz = folder / "modes.npz"
    npz.write_bytes(npz.read_bytes()[:-10])  # damaged: extracted again, not trusted
    ds[0]
    assert len(calls) == 3
    other = InstanceDataset(data / "video", "val", observation="extracted", max_modes=8,
                            options={"extract": {"prominence": 0.7}})
    other[0]
    assert len(calls) == 4 and len(list(cached.iterdir())) == 2


def test_extracted_without_video_is_one_clear_error(data):
    ds = InstanceDataset(data / "train", "train", observation="extracted")
    with pytest.raises(DatasetError, match=r"tinycube-train-00000: .*needs a video.*no-video"):
        ds[0]
    with pytest.raises(Exception, match="n_modes must be an integer"):
        InstanceDataset(data / "train", "train", max_modes=0)


def test_the_documented_training_example_runs(data, capsys):
    text = (Path(__file__).parents[1] / "docs" / "learning.md").read_text()
    (code,) = [block for block in re.findall(r"```python\n(.*?)```", text, re.S)
               if "InstanceDataset(DATA" in block]
    code = code.replace('"data/cube_defects/train"', repr(str(data / "train")))
    exec(compile(code, "docs/learning.md", "exec"), {"__name__": "docs_example"})
    out = capsys.readouterr().out
    assert re.search(r"inputs\s+gamma\s+20x729x2", out)
    fit = re.search(r"(ridge fit on 3 instances: training residual|epoch 1: loss) (\S+)", out)
    assert fit is not None and np.isfinite(float(fit[2]))


def test_cached_items_are_the_items_and_skip_the_observation(data, monkeypatch, tmp_path):
    import vvtbench.observe

    fresh = InstanceDataset(data / "train", "train", max_modes=16)
    fresh_items = [fresh[i] for i in range(len(fresh))]
    cached = InstanceDataset(data / "train", "train", max_modes=16, cache_items=True,
                             cache_dir=tmp_path)
    calls = []
    real = vvtbench.observe.observe
    monkeypatch.setattr(vvtbench.observe, "observe",
                        lambda *a, **k: calls.append(1) or real(*a, **k))
    first = [cached[i] for i in range(len(cached))]
    assert len(calls) == N_TRAIN
    second = [cached[i] for i in range(len(cached))]
    assert len(calls) == N_TRAIN  # read from the cache
    for i, want in enumerate(fresh_items):
        for got in (first[i], second[i]):
            assert {k: got[k] for k in want if k not in ("inputs", "targets")} == \
                   {k: want[k] for k in want if k not in ("inputs", "targets")}
            for k, v in _flat(want).items():
                assert type(_flat(got)[k]) is type(v), k
                np.testing.assert_array_equal(_flat(got)[k], v)
    (item_file,) = (tmp_path / cached.names[0] / "items").glob("*.npz")
    item_file.write_bytes(item_file.read_bytes()[:-8])  # damaged: observed again
    cached[0]
    assert len(calls) == N_TRAIN + 1
    bare_ds = InstanceDataset(data / "train", "train", max_modes=16, cache_items=True,
                              cache_dir=tmp_path, targets=False)
    other = InstanceDataset(data / "train", "train", max_modes=12, cache_items=True,
                            cache_dir=tmp_path)
    before = len(calls)  # each dataset observed its first instance for its sizes
    assert "targets" not in bare_ds[0] and len(calls) == before
    other[0]  # other padded sizes: another item
    assert len(calls) == before + 1


def test_nodes_are_padded_to_a_stated_count_and_the_grid_follows_the_options(data):
    ds = InstanceDataset(data / "train", "train", max_modes=8, n_nodes=800,
                         options={"inference_shape": [4, 4, 4]})
    x = ds[0]["inputs"]
    assert x["gamma"].shape == (8, 800, 2) and x["active"].shape == (4, 4, 4)
    assert x["node_mask"].tolist() == [True] * 125 + [False] * 675
    assert not x["visible"][125:].any() and not x["gamma"][:, 125:].any()
    assert not x["points"][125:].any() and x["points"][:125].max() > 0
    assert InstanceDataset(data / "train", "train", options={"inference_shape": [4, 4, 4]}
                           ).layout().nodes == 125
    with pytest.raises(DatasetError, match=r"tinycube-train-00000: .*125 nodes, more than "
                                           r"the 100 .*n_nodes >= 125"):
        InstanceDataset(data / "train", "train", n_nodes=100,
                        options={"inference_shape": [4, 4, 4]})[0]


def test_a_missing_truth_chunk_is_an_error_naming_it_never_zeros(data, tmp_path):
    from vvtbench.datasets.packed import ExportError

    pack = tmp_path / "damaged.zarr"
    assert main(["export", str(data / "train"), "-o", str(pack)]) == 0
    good = InstanceDataset(pack, "train", max_modes=16)[0]["targets"]["w"]
    assert good.min() > 0
    (chunk,) = sorted(pack.glob("samples/*-00000/truth/material/stiffness/c/*"))
    rel = chunk.relative_to(pack).as_posix()
    data_bytes = chunk.read_bytes()
    chunk.unlink()
    with pytest.raises(ExportError, match=re.escape(f"chunk {rel} is missing")):
        InstanceDataset(pack, "train", max_modes=16)[0]
    chunk.write_bytes(data_bytes[:-1] + bytes([data_bytes[-1] ^ 1]))  # changed, not missing
    with pytest.raises(ExportError, match=re.escape(f"chunk {rel} differs")):
        InstanceDataset(pack, "train", max_modes=16)[0]
    chunk.write_bytes(data_bytes)
    (pack / "SHA256SUMS").unlink()  # nothing to check the chunks against: refused too
    with pytest.raises(ExportError, match="SHA256SUMS: missing"):
        InstanceDataset(pack, "train", max_modes=16)[0]
