"""Dataset readers (RealEstate10K, DL3DV, Tanks and Temples): cameras, sampling protocol, resizing, errors."""

from __future__ import annotations

import numpy as np
import pytest
from datasets_fixtures import (
    blob_centre,
    circle_trajectory,
    frame_index_of,
    landmark_pixel,
    re10k_timestamps,
    render_frame,
    write_dl3dv,
    write_re10k,
    write_tnt,
)

from navcrafter.models.camera.cameras import Intrinsics, rotation_angle_deg
from navcrafter.schemas.datasets import (
    DatasetError,
    Sample,
    open_dataset,
    opengl_to_opencv,
    read_colmap_cameras,
    resize_center_crop,
)

TRAJ = circle_trajectory()


def _check_clip(s: Sample, traj, start: int, stride: int = 1, num_frames: int = 14) -> None:
    """Frames, poses and intrinsics of a clip are those of the trajectory at start + stride * k."""
    idx = start + stride * np.arange(num_frames + 1)
    assert s.num_frames == num_frames + 1 and s.frames.shape[0] == num_frames
    np.testing.assert_array_equal(s.indices, idx)
    assert frame_index_of(s.image) == start
    assert [frame_index_of(f) for f in s.frames] == list(idx[1:])
    np.testing.assert_allclose(s.c2w, traj.c2w[idx], atol=1e-6, rtol=0)


def _blob_consistent(s: Sample, tol: float) -> None:
    """The landmark projected with the returned pose and K lands on the blob drawn in the returned frame."""
    for c2w, K, img in zip(s.c2w, s.K, s.images):
        np.testing.assert_allclose(blob_centre(img), landmark_pixel(c2w, K, TRAJ.landmark), atol=tol)


# --------------------------------------------------------------------------------------------------
# Cameras recovered from each format
# --------------------------------------------------------------------------------------------------
def test_re10k_recovers_c2w_and_pixel_intrinsics(tmp_path):
    write_re10k(tmp_path, TRAJ, "seqA")
    reader = open_dataset("re10k", tmp_path, resolution=None, start="first")
    info = reader.sequence("seqA")
    np.testing.assert_allclose(info.c2w, TRAJ.c2w, atol=1e-6, rtol=0)  # w2c in the file -> c2w
    np.testing.assert_allclose(info.K, TRAJ.K, atol=1e-9)              # normalised -> pixels
    (s,) = list(reader)
    assert s.dataset == "re10k" and s.sequence == "seqA" and s.clip_id == "re10k/seqA@0"
    assert s.image.shape == (48, 64, 3) and s.image.dtype == np.uint8 and s.frames.shape == (14, 48, 64, 3)
    _check_clip(s, TRAJ, 0)
    np.testing.assert_allclose(s.K, TRAJ.K[:15], atol=1e-9)
    np.testing.assert_array_equal(s.timestamps_us, re10k_timestamps(20)[:15])
    assert s.frame_ids == [str(t) for t in re10k_timestamps(20)[:15]]
    assert s.meta["url"].startswith("https://www.youtube.com/")
    _blob_consistent(s, tol=0.05)
    np.testing.assert_allclose(s.relative_c2w()[0], np.eye(4), atol=1e-12)


def test_re10k_jpg_frames_without_split_level(tmp_path):
    write_re10k(tmp_path, TRAJ, "seqJ", split=None, ext=".jpg")
    (s,) = list(open_dataset("re10k", tmp_path, split=None, resolution=None, start="first"))
    _check_clip(s, TRAJ, 0)
    assert s.paths[0].suffix == ".jpg"


@pytest.mark.parametrize("variant", ["plain", "downscaled", "per_frame", "nerfstudio_subfolder"])
def test_dl3dv_recovers_c2w_with_opengl_flip(tmp_path, variant):
    traj = circle_trajectory(varying_focal=variant == "per_frame")
    options: dict = {}
    if variant == "downscaled":  # json: 4x intrinsics and file_path images/..., frames in images_4/
        write_dl3dv(tmp_path, traj, "scene_a", downscale=4)
        options["images_dir"] = "images_4"
    else:
        write_dl3dv(tmp_path, traj, "scene_a", per_frame_intrinsics=variant == "per_frame",
                    nerfstudio_subfolder=variant == "nerfstudio_subfolder")
    reader = open_dataset("dl3dv", tmp_path, resolution=None, start="first", **options)
    info = reader.sequence("scene_a")
    assert info.frame_ids[:3] == ["frame_00001", "frame_00002", "frame_00003"]  # json order was shuffled
    np.testing.assert_allclose(info.c2w, traj.c2w, atol=1e-6, rtol=0)
    (s,) = list(reader)
    _check_clip(s, traj, 0)
    np.testing.assert_allclose(s.K, traj.K[:15], atol=1e-9)
    for c2w, K, img in zip(s.c2w, s.K, s.images):
        np.testing.assert_allclose(blob_centre(img), landmark_pixel(c2w, K, traj.landmark), atol=0.05)


def test_opengl_to_opencv_flips_camera_y_and_z():
    # an OpenGL camera at the origin with identity pose looks down world -z with world +y up in the image
    cv = opengl_to_opencv(np.eye(4))
    np.testing.assert_array_equal(cv[:3, 2], [0, 0, -1])  # OpenCV +z = viewing direction
    np.testing.assert_array_equal(cv[:3, 1], [0, -1, 0])  # OpenCV +y = image down
    np.testing.assert_array_equal(cv[:3, 0], [1, 0, 0])
    np.testing.assert_allclose(opengl_to_opencv(opengl_to_opencv(TRAJ.c2w)), TRAJ.c2w)


def test_dl3dv_downscaled_folder_needs_images_dir(tmp_path):
    write_dl3dv(tmp_path, TRAJ, "scene_a", downscale=4)
    with pytest.raises(DatasetError, match=r"images_4.*images_dir="):
        open_dataset("dl3dv", tmp_path, strict=True).sequence("scene_a")


def test_tnt_log_with_colmap_cameras_txt(tmp_path):
    write_tnt(tmp_path, TRAJ, "Barn", cameras_scale=2)  # cameras.txt describes 128x96 images
    reader = open_dataset("tnt", tmp_path, resolution=None, start="first")
    info = reader.sequence("Barn")
    np.testing.assert_allclose(info.c2w, TRAJ.c2w, atol=1e-6, rtol=0)
    assert info.meta["intrinsics_from"].endswith("sparse/0/cameras.txt")
    (s,) = list(reader)
    _check_clip(s, TRAJ, 0)
    np.testing.assert_allclose(s.K, TRAJ.K[:15], atol=1e-9)  # rescaled to the 64x48 images read
    assert s.frame_ids[:2] == ["000001", "000002"]
    _blob_consistent(s, tol=0.15)  # JPEG frames


def test_tnt_given_intrinsics_win_and_missing_intrinsics_error(tmp_path):
    log = write_tnt(tmp_path, TRAJ, "Barn", cameras_txt=None)
    with pytest.raises(DatasetError) as err:
        open_dataset("tnt", tmp_path).sequence("Barn")
    msg = str(err.value)
    assert log.name in msg and "intrinsics=Intrinsics(" in msg and "cameras.txt" in msg
    # given for 2x larger images: rescaled to the images read
    K = TRAJ.K[0]
    given = Intrinsics(2 * K[0, 0], 2 * K[1, 1], 2 * K[0, 2], 2 * K[1, 2], 128, 96)
    for intr in (given, {"Barn": given}):
        (s,) = list(open_dataset("tnt", tmp_path / "Barn", intrinsics=intr, resolution=None, start="first"))
        assert s.sequence == "Barn"  # root may be the scene itself
        np.testing.assert_allclose(s.K, TRAJ.K[:15], atol=1e-9)


def test_colmap_camera_models(tmp_path):
    p = tmp_path / "cameras.txt"
    p.write_text("# comment\n1 SIMPLE_PINHOLE 640 480 500 320 240\n2 OPENCV 640 480 500 510 321 241 0.1 0 0 0\n")
    cams = read_colmap_cameras(p)
    assert cams[1] == ("SIMPLE_PINHOLE", Intrinsics(500, 500, 320, 240, 640, 480))
    assert cams[2] == ("OPENCV", Intrinsics(500, 510, 321, 241, 640, 480))
    p.write_text("1 OPENCV_FISHEYE 640 480 500 510 321 241 0 0 0 0\n")
    with pytest.raises(DatasetError, match=r"cameras.txt:1: camera model OPENCV_FISHEYE is not supported"):
        read_colmap_cameras(p)


def test_package_reexports_each_format_module():
    # one module per format; the package keeps the old single-module API
    import navcrafter.schemas.datasets as datasets
    from navcrafter.schemas.datasets import base, colmap, dl3dv, realestate10k, tanksandtemples

    assert all(hasattr(datasets, name) for name in datasets.__all__)
    assert datasets.DATASET_KINDS["re10k"] is realestate10k.RealEstate10KReader
    assert datasets.DATASET_KINDS["dl3dv"] is dl3dv.DL3DVReader
    assert datasets.DATASET_KINDS["tnt"] is tanksandtemples.TanksAndTemplesReader
    assert datasets.read_colmap_cameras is colmap.read_colmap_cameras
    assert datasets.DatasetError is base.DatasetError and datasets.Sample is base.Sample


# --------------------------------------------------------------------------------------------------
# Sampling protocol
# --------------------------------------------------------------------------------------------------
def test_protocol_conditioning_frame_and_next_14(tmp_path):
    write_re10k(tmp_path, TRAJ, "seqA")
    reader = open_dataset("re10k", tmp_path, resolution=None, clips_per_dataset=6)  # 20 frames: 6 starts
    clips = list(reader)
    assert sorted(s.start for s in clips) == list(range(6))
    for s in clips:
        _check_clip(s, TRAJ, s.start)
    (s,) = list(open_dataset("re10k", tmp_path, resolution=None, num_frames=7, stride=2, clips_per_dataset=1))
    _check_clip(s, TRAJ, s.start, stride=2, num_frames=7)


def test_clips_are_deterministic_per_seed(tmp_path):
    for k in range(4):
        write_re10k(tmp_path, TRAJ, f"seq{k}")

    def draw(seed, n):
        return open_dataset("re10k", tmp_path, clips_per_dataset=n, seed=seed, resolution=None)

    plan = draw(3, 10).plan()
    assert plan == draw(3, 10).plan()
    clips = list(draw(3, 10))
    assert [(s.sequence, s.start) for s in clips] == plan
    again = list(draw(3, 10))
    assert all(np.array_equal(a.frames, b.frames) for a, b in zip(clips, again))
    assert len(set(plan)) == 10                                  # no clip drawn twice
    counts = np.unique([n for n, _ in plan], return_counts=True)[1]
    assert counts.max() - counts.min() <= 1                      # one clip per sequence per round
    assert draw(3, 3).plan() == plan[:3]                         # a prefix of the longer draw
    assert len({tuple(draw(seed, 10).plan()) for seed in range(5)}) > 1
    assert len(draw(0, 100).plan()) == 4 * 6                     # every (sequence, start) once, then stop
    assert len(draw(0, None).plan()) == 4                        # default: one clip per sequence
    firsts = open_dataset("re10k", tmp_path, start="first", clips_per_dataset=10).plan()
    assert sorted(firsts) == [(f"seq{k}", 0) for k in range(4)]


# --------------------------------------------------------------------------------------------------
# Resizing and cropping
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("size", [(256, 256), (32, 40), (48, 64), (96, 128), (100, 50), (30, 30), (47, 61)])
def test_resize_center_crop_adjusts_intrinsics(size):
    H, W = size
    c2w, K = TRAJ.c2w[5], TRAJ.K[5]
    img = render_frame(5, c2w, K, 64, 48, TRAJ.landmark, sigma=2.5)
    out, K2 = resize_center_crop(img, K, H, W)
    assert out.shape == (H, W, 3) and out.dtype == np.uint8
    # the landmark, projected with the new K, is where the resampled image shows it
    # (measured error < 0.03 px; a half-pixel convention slip would be >= 0.3 px at these scales)
    np.testing.assert_allclose(blob_centre(out), landmark_pixel(c2w, K2, TRAJ.landmark), atol=0.06)
    # the crop is centred: the ray through the old image centre goes through the new one
    ray = np.linalg.inv(K) @ [32, 24, 1]
    centre = K2 @ ray
    np.testing.assert_allclose(centre[:2] / centre[2], [W / 2, H / 2], atol=1e-9)
    if H * 64 == W * 48:  # same aspect ratio: no crop, normalised positions are unchanged
        uv, uv2 = landmark_pixel(c2w, K, TRAJ.landmark), landmark_pixel(c2w, K2, TRAJ.landmark)
        np.testing.assert_allclose(uv2 / [W, H], uv / [64, 48], atol=1e-12)


def test_reader_resolution_keeps_cameras_consistent(tmp_path):
    write_re10k(tmp_path, TRAJ, "seqA")
    (s,) = list(open_dataset("re10k", tmp_path, resolution=256, clips_per_dataset=1))
    assert s.images.shape == (15, 256, 256, 3)
    _check_clip(s, TRAJ, s.start)
    _blob_consistent(s, tol=0.1)
    assert s.intrinsics(0).width == 256
    # forward axis of the recovered pose points at the circled point (pose semantics, not just numbers)
    fwd = s.c2w[0, :3, 2]
    to_centre = np.array([0.0, 0.3, 5.0]) - s.c2w[0, :3, 3]
    assert np.degrees(np.arccos(fwd @ to_centre / np.linalg.norm(to_centre))) < 2.0
    assert rotation_angle_deg(s.c2w[0, :3, :3], TRAJ.c2w[s.start, :3, :3]) < 1e-4


# --------------------------------------------------------------------------------------------------
# Errors and skipping
# --------------------------------------------------------------------------------------------------
def _edit_line(path, lineno, fn):
    lines = path.read_text().splitlines()
    lines[lineno - 1] = fn(lines[lineno - 1])
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("edit,match", [
    (lambda ln: ln.rsplit(" ", 1)[0], r"seqA\.txt:5: expected 19 numbers"),
    (lambda ln: ln.replace(" 0.0 0.0 ", " 0.0 zero ", 1), r"seqA\.txt:5: expected numbers"),
    (lambda ln: "1.5 " + ln.split(" ", 1)[1], r"seqA\.txt:5: the timestamp '1\.5' is not an integer"),
])
def test_re10k_malformed_line(tmp_path, edit, match):
    txt = write_re10k(tmp_path, TRAJ, "seqA")
    _edit_line(txt, 5, edit)
    with pytest.raises(DatasetError, match=match):
        open_dataset("re10k", tmp_path).sequence("seqA")


def test_re10k_other_errors(tmp_path):
    txt = write_re10k(tmp_path, TRAJ, "seqA")
    lines = txt.read_text().splitlines()
    txt.write_text("\n".join(lines[1:]) + "\n")  # URL line lost
    with pytest.raises(DatasetError, match=r"seqA\.txt:1: the first line should be the YouTube URL"):
        open_dataset("re10k", tmp_path).sequence("seqA")
    txt.write_text("\n".join(lines) + "\n")
    frame = tmp_path / "test" / "seqA" / f"{re10k_timestamps(20)[3]}.png"
    frame.unlink()
    with pytest.raises(DatasetError, match=r"1 of 20 frames.*missing_frames='drop'"):
        open_dataset("re10k", tmp_path).sequence("seqA")
    info = open_dataset("re10k", tmp_path, missing_frames="drop").sequence("seqA")
    assert len(info) == 19 and frame.stem not in info.frame_ids
    np.testing.assert_allclose(info.c2w[3], TRAJ.c2w[4], atol=1e-6)
    with pytest.raises(DatasetError, match=r"no frames folder"):
        write_re10k(tmp_path, TRAJ, "seqB", frames=False)
        open_dataset("re10k", tmp_path).sequence("seqB")
    with pytest.raises(DatasetError, match="is not a folder"):
        open_dataset("re10k", tmp_path / "nowhere")
    with pytest.raises(ValueError, match="unknown dataset kind"):
        open_dataset("co3d", tmp_path)


def test_too_few_frames_and_corrupt_frame(tmp_path):
    write_re10k(tmp_path, circle_trajectory(10), "short")
    reader = open_dataset("re10k", tmp_path)
    with pytest.raises(DatasetError, match=r"'short' has 10 frames but a clip needs 15 .*lower num_frames"):
        reader.valid_starts(reader.sequence("short"))
    bad = tmp_path / "test" / "short" / f"{re10k_timestamps(10)[2]}.png"
    bad.write_bytes(bad.read_bytes()[:60])
    with pytest.raises(DatasetError, match=r"cannot read image .*short.*\.png"):
        open_dataset("re10k", tmp_path, num_frames=5).clip("short", 0)


def test_dl3dv_and_tnt_malformed(tmp_path):
    js = write_dl3dv(tmp_path / "dl", TRAJ, "scene_a")
    js.write_text(js.read_text()[:-20])
    with pytest.raises(DatasetError, match=r"transforms\.json: not valid JSON"):
        open_dataset("dl3dv", tmp_path / "dl").sequence("scene_a")
    js = write_dl3dv(tmp_path / "dl", TRAJ, "scene_b")
    js.write_text(js.read_text().replace('"transform_matrix"', '"transform"', 1))
    with pytest.raises(DatasetError, match=r"frames\[\d+\]: needs 'file_path' and 'transform_matrix'"):
        open_dataset("dl3dv", tmp_path / "dl").sequence("scene_b")
    log = write_tnt(tmp_path / "tnt", TRAJ, "Barn")
    text = log.read_text().splitlines()
    log.write_text("\n".join(text[:-2]) + "\n")
    with pytest.raises(DatasetError, match=r"Barn_COLMAP_SfM\.log: 98 non-empty lines is not a multiple of 5"):
        open_dataset("tnt", tmp_path / "tnt").sequence("Barn")
    log.write_text("\n".join(text[:-5]) + "\n")
    with pytest.raises(DatasetError, match=r"has 19 cameras but .*images has 20 images"):
        open_dataset("tnt", tmp_path / "tnt").sequence("Barn")
    log.write_text("\n".join(text).replace("0 0 0\n", "0 0\n", 1) + "\n")
    with pytest.raises(DatasetError, match=r"\.log:1: expected a metadata line of 3 integers"):
        open_dataset("tnt", tmp_path / "tnt").sequence("Barn")


def test_bad_sequences_are_skipped_with_a_reason(tmp_path):
    for k in range(3):
        write_re10k(tmp_path, TRAJ, f"good{k}")
    _edit_line(write_re10k(tmp_path, TRAJ, "malformed"), 7, lambda ln: ln + " 1.0")
    write_re10k(tmp_path, circle_trajectory(8), "short")
    write_re10k(tmp_path, TRAJ, "corrupt")
    (tmp_path / "test" / "corrupt" / f"{re10k_timestamps(20)[0]}.png").write_bytes(b"not a png")
    reader = open_dataset("re10k", tmp_path, start="first", resolution=None)
    clips = list(reader)
    assert sorted(s.sequence for s in clips) == ["good0", "good1", "good2"]
    assert set(reader.skipped) == {"malformed", "short", "corrupt"}
    assert "malformed.txt:7: expected 19 numbers" in reader.skipped["malformed"]
    assert "has 8 frames but a clip needs 15" in reader.skipped["short"]
    assert "cannot read image" in reader.skipped["corrupt"]
    # a clip budget is still met from the good sequences
    reader = open_dataset("re10k", tmp_path, clips_per_dataset=5, resolution=(24, 32))
    assert len(list(reader)) == 5 and len(reader.skipped) == 3
    with pytest.raises(DatasetError, match="expected 19 numbers"):
        list(open_dataset("re10k", tmp_path, strict=True, sequences=["good0", "malformed"]))
    with pytest.raises(DatasetError, match=r"every sequence was skipped:\n  short: "):
        list(open_dataset("re10k", tmp_path, sequences=["short"]))


def test_dl3dv_and_tnt_skip_bad_scenes(tmp_path):
    write_dl3dv(tmp_path / "dl", TRAJ, "good")
    (tmp_path / "dl" / "no_poses" / "images_4").mkdir(parents=True)
    reader = open_dataset("dl3dv", tmp_path / "dl", resolution=None)
    assert [s.sequence for s in reader] == ["good"]
    assert "no transforms.json" in reader.skipped["no_poses"]
    write_tnt(tmp_path / "tnt", TRAJ, "Barn")
    write_tnt(tmp_path / "tnt", TRAJ, "Truck", cameras_txt=None)
    reader = open_dataset("tnt", tmp_path / "tnt", resolution=None)
    assert [s.sequence for s in reader] == ["Barn"]
    assert "intrinsics=" in reader.skipped["Truck"]
