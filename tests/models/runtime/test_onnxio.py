"""Model directories: checksums remembered across loads, external data confined to the directory."""

from __future__ import annotations

import shutil

import pytest
import torch

from navcrafter.models.runtime import onnxio


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("onnxio") / "geometry"
    torch.manual_seed(0)
    info = onnxio.export_graph(torch.nn.Linear(64, 64), (torch.randn(2, 64),), d / "geometry.onnx",
                               input_names=["x"], output_names=["y"])
    onnxio.write_manifest(d, kind="geometry", architecture="linear", config={}, weights={"source": "random"},
                          graphs={"geometry": info})
    return d


def test_checksums_are_remembered_until_a_file_changes(model_dir, tmp_path, monkeypatch):
    monkeypatch.setenv("NAVCRAFTER_CHECKSUM_CACHE", str(tmp_path / "cache.json"))
    d = tmp_path / "m"
    shutil.copytree(model_dir, d)
    calls = []
    real = onnxio.sha256_file
    monkeypatch.setattr(onnxio, "sha256_file", lambda p, *a: calls.append(p.name) or real(p, *a))
    onnxio.load_manifest(d, "geometry")
    assert sorted(calls) == ["geometry.onnx", "geometry.onnx.data"]
    onnxio.load_manifest(d, "geometry")  # a new process would read the same cache file
    assert len(calls) == 2
    data = d / "geometry.onnx.data"
    raw = bytearray(data.read_bytes())
    raw[0] ^= 0xFF
    data.write_bytes(bytes(raw))  # new mtime: hashed again, and the change is found
    with pytest.raises(onnxio.ModelDirError, match="checksum of geometry.onnx.data"):
        onnxio.load_manifest(d, "geometry")
    assert calls[-1] == "geometry.onnx.data"
    with pytest.raises(onnxio.ModelDirError):  # a mismatch is never remembered as verified
        onnxio.load_manifest(d, "geometry")


@pytest.mark.parametrize("location, message", [("../outside.data", "lies outside"),
                                               ("other.data", "not covered by the manifest")])
def test_external_data_must_stay_inside_and_be_covered(model_dir, tmp_path, monkeypatch, location, message):
    import onnx

    monkeypatch.setenv("NAVCRAFTER_CHECKSUM_CACHE", str(tmp_path / "cache.json"))
    d = tmp_path / "m"
    shutil.copytree(model_dir, d)
    shutil.copy(d / "geometry.onnx.data", tmp_path / "outside.data")
    shutil.copy(d / "geometry.onnx.data", d / "other.data")
    graph = onnx.load(str(d / "geometry.onnx"), load_external_data=False)
    for t in graph.graph.initializer:
        for e in t.external_data:
            if e.key == "location":
                e.value = location
    onnx.save(graph, str(d / "geometry.onnx"))
    info = onnxio.GraphInfo(file="geometry.onnx", inputs=["x"], outputs=["y"])
    onnxio.write_manifest(d, kind="geometry", architecture="linear", config={}, weights={"source": "random"},
                          graphs={"geometry": info})  # checksums of the tampered graph: they match
    with pytest.raises(onnxio.ModelDirError, match=message):
        onnxio.load_manifest(d, "geometry")
    assert onnxio.external_data_files(model_dir / "geometry.onnx") == {"geometry.onnx.data"}
