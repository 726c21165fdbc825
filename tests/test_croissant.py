"""Croissant 1.1 of a stacked export (vvtbench.datasets.croissant): mlcroissant validates it and
reads
the instance records; every listed file's sha256 is the file's."""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

import pandas as pd
import pytest
from test_export import make_family_samples

from vvtbench.cli.export import main as export_main

mlc = pytest.importorskip("mlcroissant")


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("croissant")
    samples = make_family_samples(root, {"test": 3})
    out = root / "tiny"
    assert export_main([str(samples), "-o", str(out), "--layout", "stacked"]) == 0
    return out


def test_mlcroissant_validates_and_loads_the_index(exported, caplog):
    with caplog.at_level(logging.WARNING):
        dataset = mlc.Dataset(jsonld=str(exported / "croissant.json"))
    assert not [r for r in caplog.records if "@context" in r.getMessage()]
    records = list(dataset.records(record_set="instances"))
    index = pd.read_parquet(exported / "index.parquet")
    assert len(records) == len(index) == 3

    def text(v):
        return v.decode() if isinstance(v, bytes) else v

    for rec, (_, row) in zip(records, index.iterrows(), strict=True):
        assert text(rec["instances/sample"]) == row["sample"]
        assert int(rec["instances/seed"]) == int(row["seed"])
        assert text(rec["instances/store"]) == "tiny_defects/test.zarr"
        assert rec["instances/scene.material.E"] == pytest.approx(row["scene.material.E"])


def test_croissant_lists_files_with_their_sha256_and_rai(exported):
    meta = json.loads((exported / "croissant.json").read_text())
    assert meta["conformsTo"] == "http://mlcommons.org/croissant/1.1"
    objects = [d for d in meta["distribution"] if d["@type"] == "cr:FileObject"]
    assert {"index.parquet", "README.md", "tiny_defects/test.zarr/zarr.json"} <= {
        d["contentUrl"] for d in objects}
    for d in objects:
        assert d["sha256"] == hashlib.sha256((exported / d["contentUrl"]).read_bytes()).hexdigest()
    sets = [d for d in meta["distribution"] if d["@type"] == "cr:FileSet"]
    assert [d["includes"] for d in sets] == ["tiny_defects/test.zarr/**"]
    fields = {f["name"]: f["dataType"] for f in meta["recordSet"][0]["field"]}
    assert fields["seed"] == "sc:Integer" and fields["sample"] == "sc:Text"
    assert fields["scene.material.E"] == "sc:Float"
    assert set(fields) == set(pd.read_parquet(exported / "index.parquet").columns)
    assert meta["rai:dataCollectionType"] == ["Simulation"]
    assert "no personal data" in meta["rai:personalSensitiveInformation"]
    assert meta["license"].startswith("https://creativecommons.org/")
    assert meta["vvtbench:version"] in meta["prov:wasGeneratedBy"]["name"]
    assert meta["rai:dataLimitations"] and meta["rai:dataUseCases"]
