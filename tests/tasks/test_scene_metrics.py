"""The evaluation suite over a finished store: `evaluate-store` flow, its tables, report and caching."""

from __future__ import annotations

import shutil
from collections import Counter

import numpy as np
import pytest
import zarr
from helpers import DEMO, TINY
from typer.testing import CliRunner

from navcrafter.flows.cli import app
from navcrafter.schemas.layout import EVALUATE, SCORE, SYNTHESIZE
from navcrafter.schemas.store import Store
from navcrafter.tasks.score import TABLES, clip_indices, evaluation_markdown, pose_error_rows, row, scored_frames


@pytest.fixture(scope="module")
def evaluated(full_run, tmp_path_factory, prefect_api_url):
    from navcrafter.flows.evaluate import evaluate_store

    store = tmp_path_factory.mktemp("evaluate") / "store"
    shutil.copytree(full_run[0], store)
    weights = tmp_path_factory.mktemp("no-weights")  # empty: weight-based metrics must say unavailable
    config = TINY.model_copy(update={"evaluation": TINY.evaluation.model_copy(update={"weights_dir": weights})})
    return store, config, evaluate_store(str(store), config)


@pytest.mark.system
def test_every_finished_scene_gets_every_table(evaluated, full_run):
    store, _, result = evaluated
    done = {r.scene_id for r in full_run[1].scenes if r.status == "done"}
    assert len(done) == len(DEMO) and not result.failed
    per_scene = {r["scene_id"] for r in result.rows if r["scene_id"]}
    assert per_scene == done
    for sid in done:
        tables = {r["table"] for r in result.rows if r["scene_id"] == sid}
        assert tables == set(TABLES) - {"II"}, sid  # II (FID / FVD) is over all scenes
    by = {(r["scene_id"], r["table"], r["metric"]): r for r in result.rows}
    s = Store(str(store))
    for sid in done:
        # V is the scene's stored evaluation, then its recorded step times (Runtime in minutes, stages in seconds)
        metrics = s.scene(sid).status(EVALUATE).attrs["metrics"]
        assert by[(sid, "V", "Coverage")]["value"] == pytest.approx(metrics["coverage"])
        assert by[(sid, "V", "Collisions")]["value"] == metrics["collisions"]
        assert by[(sid, "V", "time: synthesize")]["value"] > 0 and by[(sid, "V", "time: plan")]["unit"] == "s"
        stages = ("geometry", "plan", "synthesize", "lift", "export", "evaluate")
        parts = [by[(sid, "V", f"time: {n}")]["value"] for n in stages]
        assert by[(sid, "V", "Runtime")]["unit"] == "min" and "4.79" in by[(sid, "V", "Runtime")]["note"]
        assert by[(sid, "V", "Runtime")]["value"] == pytest.approx(sum(parts) / 60)
        v_metrics = [m for (i, t, m) in by if i == sid and t == "V"]
        assert v_metrics == ["Coverage", "Noise ratio", "F-score", "Collisions", "Runtime"] + [
            f"time: {n}" for n in stages]
        # I: the honest simulated video model drifts from the requested cameras and hallucinates what the cloud
        # does not show, so its frames differ from the truth at those cameras (the perfect preset gives 100 dB)
        assert 5.0 < by[(sid, "I", "PSNR")]["value"] < 60.0
        assert 0.0 < by[(sid, "I", "SSIM")]["value"] < 0.99
        # III: COLMAP ran on every clip; tiny 64x64 clips may not register, which must then be said
        reg = by[(sid, "III", "registered")]
        assert reg["status"] == "ok" and 0 <= reg["value"] <= 1 and "registered by COLMAP" in reg["note"]
        assert ("unregistered frames: iteration" in reg["note"]) == (reg["value"] < 1)
        for m in ("R_err", "T_err", "R_err sum", "T_err sum"):
            r = by[(sid, "III", m)]
            assert (r["status"] == "ok" and r["value"] >= 0) or (r["status"] == "failed" and r["note"])
        assert by[(sid, "III", "R_err")]["unit"] == "rad, per-frame mean"
        # IV: the fit did not run (fit.enabled is false), and it says so
        assert {by[(sid, "IV", m)]["status"] for m in ("PSNR", "SSIM", "LPIPS")} == {"unavailable"}
        assert "fit.enabled" in by[(sid, "IV", "PSNR")]["note"]


@pytest.mark.system
def test_metrics_without_weights_are_unavailable_not_invented(evaluated):
    _, _, result = evaluated
    lp = [r for r in result.rows if r["metric"] == "LPIPS" and r["table"] == "I"]
    assert lp and all(r["status"] == "unavailable" and r["value"] is None for r in lp)
    assert all(".pth" in r["note"] and "random weights" in r["note"] for r in lp)  # names the file and the rule
    dist = {r["metric"]: r for r in result.rows if r["scene_id"] is None}
    assert set(dist) == {"FID", "FVD"} and {r["table"] for r in dist.values()} == {"II"}
    assert all(r["status"] == "unavailable" and r["value"] is None for r in dist.values())


@pytest.mark.system
def test_tables_report_and_artifacts_are_written(evaluated):
    from prefect.artifacts import Artifact

    store, _, result = evaluated
    s = Store(str(store))
    table = s.tables.read("evaluations").to_pylist()
    mine = [r for r in table if r["evaluation_id"] == result.evaluation_id]
    assert len(mine) == len(result.rows) and all(r["backend"] == "simulation" for r in mine)
    md = (store / result.report).read_text()
    assert "SIMULATION MODE" in md
    for t, title in TABLES.items():
        assert f"## Table {t}: {title}" in md
    for name in DEMO:
        assert name in md
    body = [line for line in md.splitlines() if line.startswith("|")]
    assert body and all(line.count("|") == body[0].count("|") or line.startswith("| scene") or
                        line.startswith("|---") for line in body[:2])
    assert (store / f"evaluations/{result.evaluation_id}/report.json").is_file()
    art = Artifact.get(key="evaluation-report")
    assert art is not None and "## Table III: Camera pose errors" in art.data


@pytest.mark.system
def test_scoring_again_reads_the_scores_back(evaluated, prefect_api_url):
    from navcrafter.flows.evaluate import evaluate_store

    store, config, first = evaluated
    again = evaluate_store(str(store), config)
    assert again.evaluation_id != first.evaluation_id
    assert [(r["scene_id"], r["metric"], r["value"]) for r in again.rows] == \
        [(r["scene_id"], r["metric"], r["value"]) for r in first.rows]
    events = Store(str(store)).tables.read("steps").to_pylist()
    done = Counter(e["scene_id"] for e in events if e["step"] == SCORE.path and e["event"] == "completed")
    assert set(done.values()) == {1}  # each scene scored once
    # a changed evaluation setting is a different score
    changed = config.model_copy(update={"evaluation": config.evaluation.model_copy(update={"pose_frames": 5})})
    third = evaluate_store(str(store), changed, scene_ids=[first.rows[0]["scene_id"]])
    reg = next(r for r in third.rows if r["metric"] == "registered")
    assert "of 12 frames registered" in reg["note"]  # frames 0-5 of each of the 2 clips (of 9 frames)
    spaced = config.model_copy(update={"evaluation": config.evaluation.model_copy(
        update={"pose_frames": 5, "frame_choice": "spaced"})})
    fourth = evaluate_store(str(store), spaced, scene_ids=[first.rows[0]["scene_id"]])
    reg = next(r for r in fourth.rows if r["metric"] == "registered")
    assert "of 10 frames registered" in reg["note"]  # 5 of the 9 frames of each of the 2 clips, evenly spaced


@pytest.mark.system
def test_reference_check_detects_frames_that_do_not_match_their_cameras(evaluated, tmp_path):
    """Table I is a real comparison: frames that are not the requested views score badly."""
    from navcrafter.tasks.score import synthesis_rows

    store, config, result = evaluated
    sid = result.rows[0]["scene_id"]
    broken = tmp_path / "store"
    shutil.copytree(store, broken)
    arr = zarr.open_group(str(broken / "scenes" / sid / SYNTHESIZE.group_path(1)), mode="r+")["frames"]
    arr[:] = np.asarray(arr[:])[::-1]  # the clip played backwards: right images, wrong cameras
    scene = Store(str(broken)).scene(sid)
    rows = {r["metric"]: r for r in synthesis_rows(scene, config, 1)}
    assert rows["PSNR"]["value"] < 40 and rows["SSIM"]["value"] < 0.99


def test_clip_indices_and_markdown_shape():
    assert clip_indices(81, 14).tolist()[0] == 0 and clip_indices(81, 14).tolist()[-1] == 80
    assert len(clip_indices(81, 14)) == 14 and clip_indices(5, 14).tolist() == [0, 1, 2, 3, 4]
    rows = [row("I", "PSNR", 30.0, "dB", scene_id="a" * 64), row("I", "LPIPS", status="unavailable",
                                                                  note="x.pth missing", scene_id="a" * 64),
            row("II", "FID", status="unavailable", note="y missing")]
    md = evaluation_markdown("e1", rows, {"a" * 64: "room.png"}, "onnx")
    assert "SIMULATION" not in md and "| room.png `aaaaaaaaaaaa` | 30 | unavailable [1] |" in md
    assert "| all scenes | unavailable [2] |" in md
    assert "1. unavailable: x.pth missing" in md and "2. unavailable: y missing" in md


def test_first_frames_are_the_default_image_and_colmap_frames():
    """The paper's protocol: frames 1..14 after the conditioning frame for the image metrics, 0..14 for COLMAP."""
    from navcrafter.schemas.config import EvaluationConfig

    cfg = EvaluationConfig()
    assert cfg.frame_choice == "first" and cfg.pose_frames == 14
    image, pose = scored_frames(81, cfg)
    assert image.tolist() == list(range(1, 15)) and pose.tolist() == list(range(0, 15))
    image, pose = scored_frames(9, cfg)  # a clip shorter than the protocol: cut at its end
    assert image.tolist() == list(range(1, 9)) and pose.tolist() == list(range(0, 9))
    image, pose = scored_frames(81, EvaluationConfig(pose_frames=5))
    assert image.tolist() == [1, 2, 3, 4, 5] and pose.tolist() == [0, 1, 2, 3, 4, 5]
    spaced = EvaluationConfig(frame_choice="spaced")
    image, pose = scored_frames(81, spaced)
    assert image.tolist() == pose.tolist() == clip_indices(81, 14).tolist()
    assert image[0] == 0 and image[-1] == 80


def _pose_result(r_deg: list[float], t: list[float], registered: list[bool]) -> dict:
    """A camera_guidance_precision result (the fields the rows read) with per-frame errors, frame 0 the reference."""
    n, ok = len(registered), np.asarray(registered)
    r, tt = np.where(ok, r_deg, np.nan), np.where(ok, t, np.nan)
    m = int(ok.sum()) - 1
    mean = (lambda x: float(np.nansum(x) / m)) if m > 0 else (lambda x: float("nan"))
    return {"n_frames": n, "n_registered": int(ok.sum()), "R_err_deg_sum": float(np.nansum(r)),
            "R_err_deg_mean": mean(r), "T_err_sum": float(np.nansum(tt)),
            "T_err_mean": mean(tt), "recovery": {"registered": ok.tolist()},
            "reason": "" if ok.all() else f"{n - ok.sum()} of {n} frames not registered"}


def test_pose_rows_headline_is_the_per_frame_mean_in_radians():
    a = _pose_result([0.0, 1.0, 2.0, 3.0, 6.0], [0.0, 0.1, 0.2, 0.3, 0.4], [True] * 5)
    b = _pose_result([0.0, 4.0, 8.0, 99.0], [0.0, 0.5, 0.7, 9.0], [True, True, True, False])
    rows = {r["metric"]: r for r in pose_error_rows([("iteration 1", a, np.arange(5)),
                                                     ("iteration 2", b, np.array([0, 3, 6, 8]))], "COLMAP")}
    assert list(rows) == ["R_err", "T_err", "R_err sum", "T_err sum", "registered"]
    assert {r["table"] for r in rows.values()} == {"III"}
    # clip a: 12 deg over 4 frames (the reference excluded); clip b: 12 deg over its 2 registered frames
    assert rows["R_err"]["value"] == pytest.approx(np.mean([np.deg2rad(12.0 / 4), np.deg2rad(12.0 / 2)]))
    assert rows["R_err"]["unit"] == "rad, per-frame mean"
    assert rows["T_err"]["value"] == pytest.approx(np.mean([1.0 / 4, 1.2 / 2]))
    assert rows["R_err sum"]["value"] == pytest.approx(12.0) and rows["R_err sum"]["unit"] == "deg, per clip"
    assert rows["T_err sum"]["value"] == pytest.approx(np.mean([1.0, 1.2]))
    reg = rows["registered"]
    assert reg["value"] == pytest.approx(8 / 9) and reg["unit"] == "fraction"
    assert "8 of 9 frames registered by COLMAP" in reg["note"]
    assert "unregistered frames: iteration 2: 8" in reg["note"]  # the clip-frame index, not the position
    assert "iteration 2: 1 of 4 frames not registered" in rows["R_err"]["note"]
    # one clip: the headline is deg2rad of its per-frame mean, the sum column its sum
    one = {r["metric"]: r for r in pose_error_rows([("", a, np.arange(5))], "x", scene_id="s")}
    assert one["R_err"]["value"] == pytest.approx(np.deg2rad(3.0)) and one["R_err sum"]["value"] == 12.0
    assert one["registered"]["note"].endswith("every frame registered") and one["R_err"]["scene_id"] == "s"
    # no clip COLMAP could compare: every error fails, with the reason; registered is still reported
    c = {**_pose_result([0.0, 1.0], [0.0, 0.1], [True, False]), "R_err_deg_sum": float("nan"),
         "T_err_sum": float("nan")}
    failed = {r["metric"]: r for r in pose_error_rows([("", c, np.arange(2))], "x")}
    assert {failed[m]["status"] for m in ("R_err", "T_err", "R_err sum", "T_err sum")} == {"failed"}
    assert failed["registered"]["value"] == 0.5 and "unregistered frames: 1" in failed["registered"]["note"]


def test_report_titles_are_the_papers():
    rows = [row(t, "m", 1.0, scene_id=None if t == "II" else "b" * 64) for t in ("I", "II", "III", "IV", "V")]
    md = evaluation_markdown("e2", rows, {}, "onnx")
    titles = [line for line in md.splitlines() if line.startswith("## ")]
    assert titles == ["## Table I: Novel-view synthesis quality", "## Table II: FID / FVD",
                      "## Table III: Camera pose errors", "## Table IV: 3D scene reconstruction (3DGS)",
                      "## Table V: Planning: coverage, noise, F-score, runtime"]
    last = md.rstrip().splitlines()[-1]
    assert last.startswith("Table VI (3DGS ablation)") and "benchmarks/fitting.py" in last


def test_cli_evaluate_refuses_a_store_without_finished_scenes(tmp_path):
    res = CliRunner().invoke(app, ["evaluate", str(tmp_path / "nope")])
    assert res.exit_code == 2 and "no navcrafter store" in res.output
    Store(str(tmp_path / "empty"))
    res = CliRunner().invoke(app, ["evaluate", str(tmp_path / "empty")])
    out = " ".join(res.output.split())
    assert res.exit_code == 2 and "no finished scenes" in out and "navcrafter explore" in out


def test_evaluate_help_lists_every_option():
    import typer.main

    command = typer.main.get_command(app).commands["evaluate"]
    res = CliRunner().invoke(app, ["evaluate", "--help"], terminal_width=200)
    assert res.exit_code == 0
    options = [o for p in command.params if getattr(p, "opts", None) for o in p.opts if o.startswith("--")]
    assert "--eval-weights" in options and all(o in res.output for o in options)


# --------------------------------------------------------------------------------------------------
# Scene metrics (tasks/scene_metrics.compute_metrics): true camera path, per iteration, close frames
# --------------------------------------------------------------------------------------------------
def _wall_scene(distance: float):
    """A 10 m x 10 m wall 0.1 m thick, its face ``distance`` m in front of a camera at the origin looking
    along +z (OpenCV identity pose)."""
    import open3d as o3d

    from navcrafter.models.simulation.scenes import Light, SceneObject, SimScene

    box = o3d.geometry.TriangleMesh.create_box(10.0, 10.0, 0.1)
    box.translate((-5.0, -5.0, distance))
    return SimScene("wall", 0, [SceneObject("wall", box, 0)], [], Light("point", (0.0, 0.0, 0.0)), False,
                    np.eye(4), 60.0)


def test_close_frames_count_cameras_facing_a_near_surface():
    from navcrafter.models.camera.cameras import Intrinsics
    from navcrafter.models.metrics.cloud import close_frame_mask, close_frame_metrics

    scene = _wall_scene(2.0)  # wall face at z = 2 m
    K = Intrinsics.from_fov(60.0, 256, 192)  # rendered at 64x48
    poses = np.repeat(np.eye(4)[None], 4, axis=0)
    poses[0, 2, 3] = 1.8  # 0.2 m in front of the wall, facing it: close
    poses[1, 2, 3] = 0.0  # 2 m away: not close
    poses[2, 2, 3] = 1.8  # 0.2 m from the wall but looking away from it (180 deg about y): not close
    poses[2, :3, :3] = np.diag([-1.0, 1.0, -1.0])
    poses[3, 2, 3] = 1.55  # 0.45 m: closer than 2 r_safe = 0.5 m, close
    assert close_frame_mask(scene, poses, K, near_m=0.5).tolist() == [True, False, False, True]
    assert close_frame_mask(scene, poses, K, near_m=0.4).tolist() == [True, False, False, False]
    # a camera looking along the wall sees it on (nearly) half of its pixels: not "dominated"
    side = np.eye(4)
    side[:3, :3] = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # looks along +x
    side[2, 3] = 1.9
    assert close_frame_mask(scene, side[None], K, near_m=0.5).tolist() == [False]

    m = close_frame_metrics(np.array([False, False, False, True, False, True]))
    assert m == {"close_frames": pytest.approx(2 / 6), "close_frames_last_third": 0.5}
    m = close_frame_metrics(np.array([True] * 3 + [False] * 4))  # last third: the last ceil(7/3) = 3 frames
    assert m == {"close_frames": pytest.approx(3 / 7), "close_frames_last_third": 0.0}
    assert close_frame_metrics(np.zeros(0, dtype=bool)) == {"close_frames": 0.0, "close_frames_last_third": 0.0}


def test_every_scene_metric_has_a_unit():
    from navcrafter.models.metrics.cloud import unit

    for name in ("coverage", "close_frames", "close_frames_last_third", "true_quality_mean", "coverage_iter_0",
                 "coverage_iter_12", "new_surface_iter_3", "collisions"):
        assert unit(name) is not None, name
    assert unit("collisions") == "count" and unit("coverage_iter_3") == "fraction"
    assert unit("no_such_metric") is None and unit("coverage_iter_x") is None


def _done_scenes(full_run) -> list[str]:
    return sorted(r.scene_id for r in full_run[1].scenes if r.status == "done")


@pytest.mark.system
def test_per_iteration_coverage_adds_up_to_the_final_coverage(full_run):
    from navcrafter.tasks.scene_metrics import compute_metrics

    store, _ = full_run
    gained = []
    for sid in _done_scenes(full_run):
        m = compute_metrics(Store(str(store)).scene(sid), TINY)
        n = TINY.iterations
        assert {f"coverage_iter_{k}" for k in range(n + 1)} <= set(m)
        assert {f"new_surface_iter_{k}" for k in range(1, n + 1)} <= set(m) and "new_surface_iter_0" not in m
        assert m[f"coverage_iter_{n}"] == m["coverage"]
        for k in range(n + 1):
            assert 0.0 <= m[f"coverage_iter_{k}"] <= 1.0
        for k in range(1, n + 1):
            assert m[f"new_surface_iter_{k}"] == pytest.approx(m[f"coverage_iter_{k}"] - m[f"coverage_iter_{k - 1}"])
        assert m["coverage_iter_0"] + sum(m[f"new_surface_iter_{k}"] for k in range(1, n + 1)) == \
            pytest.approx(m["coverage"])
        assert 0.0 <= m["close_frames"] <= 1.0 and 0.0 <= m["close_frames_last_third"] <= 1.0
        gained.append(m["coverage"] - m["coverage_iter_0"])
    assert max(gained) > 0  # exploring adds surface somewhere


def _set_true_arrays(store, sid: str, arrays_per_clip: dict[int, dict[str, np.ndarray]]) -> None:
    from navcrafter.schemas.layout import scene_group

    for k, arrays in arrays_per_clip.items():
        g = zarr.open_group(str(store / scene_group(sid) / SYNTHESIZE.group_path(k)), mode="r+")
        for name, value in arrays.items():
            if value is None:
                if name in g:
                    del g[name]
            else:
                g.create_array(name, data=value, overwrite=True)


@pytest.mark.system
def test_collisions_and_close_frames_are_measured_at_the_true_cameras(full_run, tmp_path):
    """The metrics follow ``true_c2w`` where the synthesize step stored it, the planned path otherwise."""
    from navcrafter.models.metrics.cloud import trajectory_collisions
    from navcrafter.models.simulation.render import render
    from navcrafter.schemas.layout import PLAN
    from navcrafter.tasks.common import simulation_truth
    from navcrafter.tasks.scene_metrics import compute_metrics

    sid = _done_scenes(full_run)[0]
    store = tmp_path / "store"
    shutil.copytree(full_run[0], store)
    scene = Store(str(store)).scene(sid)
    truth = simulation_truth(scene)
    n = TINY.iterations
    planned = {k: scene.read(PLAN, k, "trajectory") for k in range(1, n + 1)}
    r_safe_m = TINY.plan.safe_radius / truth.world_scale

    # old stores: no true arrays, the planned path is measured
    _set_true_arrays(store, sid, {k: {"true_c2w": None, "true_quality": None, "true_depth": None}
                                  for k in planned})
    m = compute_metrics(scene, TINY)
    expect = trajectory_collisions(truth, np.concatenate(list(planned.values())), r_safe_m)
    assert m["collisions"] == expect["collisions"] and m["collision_rate"] == expect["collision_rate"]
    assert "true_quality_mean" not in m

    # the video model "really" took every frame 5 cm in front of the surface the input camera looks at,
    # facing it: every frame collides and is dominated by a near surface
    K = truth.intrinsics_for(64, 64)
    centre_depth = render(truth.scene, truth.photo_c2w, K, colour=False).depth[32, 32]
    assert centre_depth > 0
    near = truth.photo_c2w.copy()
    near[:3, 3] += near[:3, 2] * (centre_depth - 0.05)  # along the optical axis (a unit vector)
    world = np.eye(4)
    world[:3, :3] = truth.photo_c2w[:3, :3].T @ near[:3, :3]
    world[:3, 3] = truth.world_points(near[None, :3, 3])[0]
    np.testing.assert_allclose(truth.gt_pose(world[None])[0], near, atol=1e-9)
    fake = {k: np.repeat(world[None], len(t), axis=0) for k, t in planned.items()}
    _set_true_arrays(store, sid, {k: {"true_c2w": fake[k], "true_quality": np.full(len(t), 0.25, np.float32)}
                                  for k, t in planned.items()})
    m = compute_metrics(scene, TINY)
    total = sum(len(t) for t in planned.values())
    assert m["collisions"] == total and m["collision_rate"] == 1.0
    assert m["close_frames"] == 1.0 and m["close_frames_last_third"] == 1.0
    assert m["true_quality_mean"] == pytest.approx(0.25)

    # only the last clip was taken there: the last third of the path is the (tiny preset's) last clip
    _set_true_arrays(store, sid, {k: {"true_c2w": planned[k]} for k in range(1, n)})
    m = compute_metrics(scene, TINY)
    assert m["collisions"] >= len(planned[n]) and m["close_frames_last_third"] == 1.0
    assert m["close_frames"] < 1.0
