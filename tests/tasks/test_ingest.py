"""Ingest: every kind of bad input gets a clear error naming the file and the fix."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from navcrafter.models.simulation.backend import SimulationTruth
from navcrafter.models.simulation.render import render
from navcrafter.schemas.config import IngestConfig, RunConfig
from navcrafter.schemas.layout import INGEST
from navcrafter.schemas.store import Store
from navcrafter.tasks.ingest import IngestError, decode_image, ingest, list_collection, make_work_image, read_source

CFG = IngestConfig()


def encode(im: Image.Image, fmt: str = "PNG", **kw) -> bytes:
    buf = io.BytesIO()
    im.save(buf, format=fmt, **kw)
    return buf.getvalue()


def halves(w=120, h=80) -> Image.Image:
    a = np.zeros((h, w, 3), np.uint8)
    a[:, : w // 2] = (255, 0, 0)
    a[:, w // 2:] = (0, 0, 255)
    return Image.fromarray(a)


def test_exif_orientation_is_applied():
    exif = Image.Exif()
    exif[0x0112] = 6  # display rotated 90 degrees clockwise
    out = decode_image(encode(halves(), "JPEG", exif=exif, quality=95), "x.jpg", CFG)
    assert out.image.shape == (120, 80, 3) and out.exif_orientation == 6
    assert out.image[:50, :, 0].mean() > 200 and out.image[-50:, :, 2].mean() > 200  # red on top


@pytest.mark.parametrize("mode", ["RGBA", "LA", "P", "L", "CMYK", "I;16", "F", "1"])
def test_modes_become_rgb8(mode):
    rng = np.random.default_rng(0)
    base = Image.fromarray(rng.integers(0, 255, (80, 100, 3), dtype=np.uint8))
    if mode == "I;16":
        im = Image.fromarray((np.linspace(0, 65535, 100 * 80).reshape(80, 100)).astype(np.uint16))
    elif mode == "F":
        im = Image.fromarray(np.linspace(-1, 3, 100 * 80).reshape(80, 100).astype(np.float32))
    else:
        im = base.convert(mode)
    fmt = "TIFF" if mode in ("CMYK", "F") else "PNG"
    out = decode_image(encode(im, fmt), f"x.{fmt.lower()}", CFG)
    assert out.image.dtype == np.uint8 and out.image.shape == (80, 100, 3)
    if mode == "I;16":
        assert out.image[0, 0, 0] == 0 and out.image[-1, -1, 0] == 255  # full 16-bit range mapped
        assert (out.image[..., 0] == out.image[..., 2]).all()
    if mode == "F":
        assert out.image.min() == 0 and out.image.max() == 255


def test_alpha_is_composited_on_background():
    a = np.zeros((80, 100, 4), np.uint8)
    a[..., 0] = 255
    a[:, :50, 3] = 255  # left half opaque red, right half transparent
    out = decode_image(encode(Image.fromarray(a, "RGBA")), "a.png", CFG)
    np.testing.assert_array_equal(out.image[0, 0], [255, 0, 0])
    np.testing.assert_array_equal(out.image[0, 99], [255, 255, 255])


def test_large_images_are_downscaled_and_cropped():
    out = decode_image(encode(halves(2000, 1000)), "big.png", CFG)
    assert out.image.shape == (512, 1024, 3) and out.original_size == (2000, 1000)
    work, crop = make_work_image(out.image, 64, 64)
    assert work.shape == (64, 64, 3) and crop == (256.0, 0.0, 512, 512)


@pytest.mark.parametrize("make,cfg,match", [
    (lambda: encode(halves(40, 30)), CFG, "too small"),
    (lambda: encode(halves(200, 200)), IngestConfig(max_pixels=1000), "megapixels"),
    (lambda: b"hello, this is a note", CFG, "not an image"),
    (lambda: b"%PDF-1.4 fake", CFG, "PDF"),
    (lambda: encode(halves(300, 200))[:400], CFG, "corrupt or truncated"),
])
def test_bad_images_are_rejected_clearly(make, cfg, match):
    with pytest.raises(IngestError, match=match) as info:
        decode_image(make(), "/photos/bad.file", cfg)
    assert "/photos/bad.file" in str(info.value)


def test_bad_files_are_rejected_before_decoding(tmp_path):
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    with pytest.raises(IngestError, match="empty"):
        read_source(str(empty), CFG)
    big = tmp_path / "big.png"
    big.write_bytes(b"x" * 5000)
    with pytest.raises(IngestError, match="MiB limit"):
        read_source(str(big), IngestConfig(max_file_bytes=1000))
    with pytest.raises(IngestError, match="not found"):
        read_source(str(tmp_path / "nope.png"), CFG)


def test_list_collection_skips_hidden_and_keeps_non_images(tmp_path, demo_photos):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "x.png").write_bytes(b"1")
    (tmp_path / "notes.txt").write_text("hi")
    (tmp_path / ".hidden").mkdir()
    (tmp_path / ".hidden" / "y.png").write_bytes(b"1")
    assert [p.rsplit("/", 1)[-1] for p in list_collection(tmp_path)] == ["x.png", "notes.txt"]
    with pytest.raises(FileNotFoundError, match="demo-data"):
        list_collection(tmp_path / "missing")
    assert len(list_collection(demo_photos)) == 3  # ground truth is hidden


def test_ingest_task_records_failures_without_raising(tmp_path):
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"\xff\xd8\xff garbage")
    res = ingest(str(tmp_path / "store"), str(bad), RunConfig.load(preset="tiny"), "r")
    assert not res.ok and "corrupt" in res.error and str(bad) in res.error


def test_ingest_writes_input_and_true_working_intrinsics(tmp_path, demo_photos, tiny):
    uri = str(tmp_path / "store")
    res = ingest(uri, str(demo_photos / "room-0.png"), tiny, "r")
    assert res.ok
    scene = Store(uri).scene(res.scene_id)
    st = scene.status(INGEST)
    assert st.complete and st.attrs["source"].endswith("room-0.png")
    work = scene.read(INGEST, None, "work_image")
    assert work.shape == (64, 64, 3)
    truth = SimulationTruth.from_record(st.attrs["simulation_truth"])
    rendered = render(truth.scene, truth.photo_c2w, truth.work_intrinsics).rgb.astype(float)
    corr = np.corrcoef(rendered.reshape(-1), work.astype(float).reshape(-1))[0, 1]
    assert corr > 0.9, corr  # the working image is what the true working camera sees
    # a copy of the photo elsewhere (no ground truth beside it) ingests without simulation truth
    other = tmp_path / "copy.png"
    other.write_bytes((demo_photos / "room-0.png").read_bytes())
    res2 = ingest(str(tmp_path / "store2"), str(other), tiny, "r")
    attrs = Store(str(tmp_path / "store2")).scene(res2.scene_id).status(INGEST).attrs
    assert res2.ok and "simulation_truth" not in attrs
