"""``navcrafter models pull`` (models/zoo/hub.py), offline only: each test lays out a Hugging Face hub cache
itself (``models--org--name/{refs/main, snapshots/<commit>/..., blobs/}``, tiny files) and never touches the
network (``HF_HUB_OFFLINE=1``; the online path is exercised with the hub calls replaced)."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from types import SimpleNamespace

import pytest
from typer.testing import CliRunner

from navcrafter.models.zoo import hub
from navcrafter.models.zoo.hub import SOURCES, HubError, pull, record_snapshot, repo_folder

COMMIT = "0123456789abcdef0123456789abcdef01234567"


@pytest.fixture(autouse=True)
def _offline(monkeypatch, tmp_path):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("NAVCRAFTER_CHECKSUM_CACHE", str(tmp_path / "checksums.json"))


def lay_out(cache: Path, repo_id: str, files: dict[str, bytes], commit: str = COMMIT) -> Path:
    """The hub cache layout: content-addressed blobs, the snapshot as relative symlinks, refs/main."""
    folder = repo_folder(cache, repo_id)
    (folder / "refs").mkdir(parents=True, exist_ok=True)
    (folder / "refs" / "main").write_text(commit)
    (folder / "blobs").mkdir(exist_ok=True)
    snap = folder / "snapshots" / commit
    for name, data in files.items():
        blob = folder / "blobs" / hashlib.sha256(data).hexdigest()
        blob.write_bytes(data)
        link = snap / name
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to(os.path.relpath(blob, link.parent))
    return snap


def tiny_moge_checkpoint() -> bytes:
    """A random tiny MoGe-2 in the official model.pt layout ({"model_config", "model"})."""
    import io

    import torch

    from navcrafter.models.geometry.moge import MoGe2, MoGe2Config, moge2_state_dict_official

    torch.manual_seed(3)
    config = MoGe2Config.tiny()
    buf = io.BytesIO()
    torch.save({"model_config": config.to_official(), "model": moge2_state_dict_official(MoGe2(config))}, buf)
    return buf.getvalue()


def test_table_matches_the_loaders():
    from navcrafter.tasks.backends import ROLE_DIRS

    assert set(hub.DEFAULT_ROLES) <= set(SOURCES)
    for src in SOURCES.values():
        assert all(hub._matches(f, src.patterns) for f in src.required), src.role
        assert src.target in (*ROLE_DIRS, hub.EVAL_DIR), src.role
        assert (src.repo_id is None) == bool(src.urls), src.role
    # the file names the evaluation networks look up are the ones the eval role fetches
    from navcrafter.models.metrics.evalnets import known_weight_files

    assert {w.filename for w in known_weight_files().values()} == {u.filename for u in SOURCES["eval"].urls}
    assert SOURCES["geometry"].required == ("model.safetensors",) and SOURCES["monodepth"].required == ("model.pt",)


@pytest.mark.slow
def test_offline_pull_exports_monodepth(tmp_path):
    from navcrafter.models.runtime.onnxio import load_manifest

    cache, model_dir = tmp_path / "hub", tmp_path / "models"
    snap = lay_out(cache, "Ruicheng/moge-2-vitl-normal", {"model.pt": tiny_moge_checkpoint()})
    record_snapshot(cache, "Ruicheng/moge-2-vitl-normal", COMMIT)
    (result,) = pull(["monodepth"], cache, model_dir, local_files_only=True)
    assert result.snapshot == snap and result.files == 1 and result.exported == model_dir / "monodepth"
    manifest = load_manifest(model_dir / "monodepth", "monodepth")  # what the runtime checks at load
    assert manifest["weights"]["source"] == "checkpoint"
    assert manifest["config"]["embed_dim"] == 32  # the checkpoint's own model_config, not ViT-L
    from navcrafter.tasks.backends import model_manifests

    assert set(model_manifests(model_dir)) == {"monodepth"}


def _geometry_cache(tmp_path) -> tuple[Path, Path]:
    cache = tmp_path / "hub"
    snap = lay_out(cache, "facebook/VGGT-1B", {"model.safetensors": b"\x01" * 4096, "config.json": b"{}"})
    record_snapshot(cache, "facebook/VGGT-1B", COMMIT)
    return cache, snap


def test_offline_verification_passes_then_catches_a_corrupted_file(tmp_path):
    cache, snap = _geometry_cache(tmp_path)
    (ok,) = pull(["geometry"], cache, None, local_files_only=True, export=False)
    assert ok.files == 2 and ok.bytes == 4096 + 2
    blob = Path(os.path.realpath(snap / "model.safetensors"))
    data = bytearray(blob.read_bytes())
    data[100] ^= 0xFF  # same size, one byte flipped
    blob.write_bytes(bytes(data))
    with pytest.raises(HubError, match="model.safetensors sha256") as err:
        pull(["geometry"], cache, None, local_files_only=True, export=False)
    assert f"delete {blob}" in str(err.value) and "facebook/VGGT-1B" in str(err.value)
    blob.write_bytes(b"\x01" * 10)  # truncated
    with pytest.raises(HubError, match="has 10 bytes, 4096 were verified"):
        pull(["geometry"], cache, None, local_files_only=True, export=False)


def test_offline_missing_file_and_missing_record_are_named(tmp_path):
    cache, snap = _geometry_cache(tmp_path)
    (snap / "model.safetensors").unlink()
    with pytest.raises(HubError, match=r"missing from the offline cache .*model\.safetensors.*--role geometry"):
        pull(["geometry"], cache, None, local_files_only=True, export=False)
    # a cache that `pull` did not fill (no navcrafter-manifest.json) is refused, naming the fix
    lay_out(cache, "Ruicheng/moge-2-vitl-normal", {"model.pt": b"x"})
    with pytest.raises(HubError, match="no verification record.*with network access"):
        pull(["monodepth"], cache, None, local_files_only=True, export=False)
    # a repository not in the cache at all
    with pytest.raises(HubError, match="nvidia/difix_ref is not in the cache"):
        pull(["refiner"], cache, None, local_files_only=True, export=False)


def test_online_path_verifies_against_hub_metadata(tmp_path, monkeypatch):
    """The download path with the hub calls replaced: sizes and LFS sha256 from model_info, git blob sha1."""
    import huggingface_hub

    monkeypatch.delenv("HF_HUB_OFFLINE")
    cache = tmp_path / "hub"
    weights, config = b"\x02" * 2048, b'{"a": 1}'
    lay_out(cache, "facebook/VGGT-1B", {"model.safetensors": weights, "config.json": config})
    git_sha1 = hashlib.sha1(b"blob %d\0" % len(config) + config).hexdigest()
    lfs = SimpleNamespace(size=len(weights), sha256=hashlib.sha256(weights).hexdigest())
    siblings = [SimpleNamespace(rfilename="model.safetensors", size=len(weights), blob_id="x", lfs=lfs),
                SimpleNamespace(rfilename="config.json", size=len(config), blob_id=git_sha1, lfs=None),
                SimpleNamespace(rfilename="model.pt", size=9, blob_id="y", lfs=None)]  # not in the patterns
    calls, real_download = [], huggingface_hub.snapshot_download
    monkeypatch.setattr(huggingface_hub.HfApi, "model_info",
                        lambda self, repo_id, **kw: SimpleNamespace(sha=COMMIT, siblings=siblings))

    def fake_download(repo_id, **kw):
        if kw.get("local_files_only"):
            return real_download(repo_id, **kw)
        calls.append(kw)
        return str(repo_folder(cache, repo_id) / "snapshots" / kw["revision"])

    monkeypatch.setattr(huggingface_hub, "snapshot_download", fake_download)
    (result,) = pull(["geometry"], cache, None, export=False)
    assert result.files == 2 and calls[0]["allow_patterns"] == list(SOURCES["geometry"].patterns)
    record = json.loads((repo_folder(cache, "facebook/VGGT-1B") / hub.MANIFEST_NAME).read_text())
    files = record["snapshots"][COMMIT]["files"]
    assert files["model.safetensors"] == {"size": 2048, "sha256": lfs.sha256, "sha256_from": "hub-lfs"}
    # the record now serves offline pulls
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    pull(["geometry"], cache, None, export=False)
    monkeypatch.delenv("HF_HUB_OFFLINE")
    lfs.sha256 = "0" * 64  # the hub says something else
    with pytest.raises(HubError, match="differs from the hub's 0000"):
        pull(["geometry"], cache, None, export=False)
    siblings.pop(0)  # the hub no longer has the file the loader reads
    with pytest.raises(HubError, match="lists no model.safetensors.*fix SOURCES"):
        pull(["geometry"], cache, None, export=False)


def test_cli_pull_offline(tmp_path):
    from navcrafter.flows.cli import app

    cache, _ = _geometry_cache(tmp_path)
    runner = CliRunner()
    res = runner.invoke(app, ["models", "pull", "--role", "geometry", "--cache", str(cache), "--offline",
                              "--no-export"])
    assert res.exit_code == 0, res.output
    assert "geometry: facebook/VGGT-1B@" + COMMIT in res.output
    res = runner.invoke(app, ["models", "pull", "--role", "refiner", "--cache", str(cache), "--offline",
                              "--no-export"])
    assert res.exit_code != 0 and "nvidia/difix_ref is not in the cache" in res.output
    res = runner.invoke(app, ["models", "pull", "--role", "nope", "--cache", str(cache), "--offline"])
    assert res.exit_code != 0 and "unknown role" in res.output


def test_fun_camera_pulls_the_wan_encoders_too(tmp_path):
    """fun-camera's export needs the diffusers Wan2.1 I2V encoders: both repositories are looked up and verified;
    the two sources of the Wan repository share one record without overwriting each other's files."""
    cache = tmp_path / "hub"
    lay_out(cache, "alibaba-pai/Wan2.1-Fun-V1.1-1.3B-Control-Camera",
            {"config.json": b"{}", "diffusion_pytorch_model.safetensors": b"w" * 64, "Wan2.1_VAE.pth": b"p"})
    record_snapshot(cache, "alibaba-pai/Wan2.1-Fun-V1.1-1.3B-Control-Camera", COMMIT)
    parts = {f"{p}/config.json": b"{}" for p in ("vae", "image_encoder", "text_encoder", "transformer")}
    parts.update({"tokenizer/tokenizer_config.json": b"{}", "vae/diffusion_pytorch_model.safetensors": b"v" * 32,
                  "transformer/diffusion_pytorch_model.safetensors": b"t" * 32})
    snap = lay_out(cache, hub.WAN_I2V, parts)
    record_snapshot(cache, hub.WAN_I2V, COMMIT)
    results = pull(["fun-camera"], cache, None, local_files_only=True, export=False)
    assert [r.role for r in results] == ["wan-i2v-encoders", "fun-camera"]
    assert results[0].files == 5  # no transformer/
    assert results[1].files == 2  # the .pth pickle is not read, so not fetched or verified
    (snap / "transformer" / "diffusion_pytorch_model.safetensors").unlink()  # fun-camera does not need it
    pull(["fun-camera"], cache, None, local_files_only=True, export=False)
    with pytest.raises(HubError, match="missing from the offline cache"):
        pull(["synthesizer"], cache, None, local_files_only=True, export=False)
    with pytest.raises(HubError, match="both export MODEL_DIR/synthesizer"):
        pull(["synthesizer", "fun-camera"], cache, tmp_path / "m", local_files_only=True)


def test_eval_role_downloads_urls_records_and_exports(tmp_path, monkeypatch):
    """The evaluation networks are not on the hub: URL downloads (replaced here) are checked (torchvision's
    hash-in-name), recorded, verified offline, and copied to MODEL_DIR/eval, where the metrics look them up."""
    from dataclasses import replace

    from navcrafter.models.metrics.evalnets import find_weights, known_weight_files

    known_weight_files()  # registers the networks' files
    monkeypatch.delenv("HF_HUB_OFFLINE")
    content = {"alexnet-owt-7be5be79.pth": b"alex trunk", "alex.pth": b"lin heads"}
    good = hashlib.sha256(content["alexnet-owt-7be5be79.pth"]).hexdigest()[:8]
    urls = (hub.UrlFile("alexnet-owt-7be5be79.pth", "https://example.invalid/a", good),
            hub.UrlFile("alex.pth", "https://example.invalid/b"),
            hub.UrlFile("i3d_pretrained_400.pt", None, note="by hand"))
    monkeypatch.setitem(SOURCES, "eval", replace(SOURCES["eval"], urls=urls))
    fetched = []

    def fake_download(uf, path):
        fetched.append(uf.filename)
        path.write_bytes(content[uf.filename])

    monkeypatch.setattr(hub, "_http_download", fake_download)
    cache, model_dir = tmp_path / "hub", tmp_path / "models"
    (result,) = pull(["eval"], cache, model_dir)
    assert fetched == ["alexnet-owt-7be5be79.pth", "alex.pth"] and result.files == 2
    assert any("i3d_pretrained_400.pt" in n and "by hand" in n for n in result.notes)
    assert find_weights("lpips-alex-v0.1", model_dir / "eval") == model_dir / "eval" / "alex.pth"
    pull(["eval"], cache, None, local_files_only=True, export=False)  # verified against the record
    assert len(fetched) == 2  # nothing downloaded again
    (cache / hub.URL_CACHE / "eval" / "alex.pth").write_bytes(b"tampered")
    with pytest.raises(HubError, match="alex.pth: differs from the copy verified at download"):
        pull(["eval"], cache, None, local_files_only=True, export=False)
    (cache / hub.URL_CACHE / "eval" / "alex.pth").unlink()
    with pytest.raises(HubError, match="alex.pth .* is missing from the offline cache"):
        pull(["eval"], cache, None, local_files_only=True, export=False)
    bad = (hub.UrlFile("alexnet-owt-7be5be79.pth", "https://example.invalid/a", "00000000"),)
    monkeypatch.setitem(SOURCES, "eval", replace(SOURCES["eval"], urls=bad))
    with pytest.raises(HubError, match="does not start with 00000000"):
        pull(["eval"], cache, None, export=False)
