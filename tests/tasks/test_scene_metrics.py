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
from navcrafter.tasks.score import TABLES, clip_indices, evaluation_markdown, row


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
        assert tables == set(TABLES), sid
    by = {(r["scene_id"], r["table"], r["metric"]): r for r in result.rows}
    s = Store(str(store))
    for sid in done:
        # VI is the scene's stored evaluation, V its recorded step times
        metrics = s.scene(sid).status(EVALUATE).attrs["metrics"]
        assert by[(sid, "VI", "Coverage")]["value"] == pytest.approx(metrics["coverage"])
        assert by[(sid, "VI", "Collisions")]["value"] == metrics["collisions"]
        assert by[(sid, "V", "synthesize")]["value"] > 0
        parts = [by[(sid, "V", n)]["value"] for n in ("geometry", "plan", "synthesize", "lift", "export", "evaluate")]
        assert by[(sid, "V", "total")]["value"] == pytest.approx(sum(parts))
        # III: the simulated synthesizer renders the truth, so stored frames equal the reference renders
        assert by[(sid, "III", "PSNR")]["value"] == 100.0 and "capped" in by[(sid, "III", "PSNR")]["note"]
        assert by[(sid, "III", "SSIM")]["value"] == pytest.approx(1.0)
        # IV: COLMAP ran on every clip; tiny 64x64 clips may not register, which must then be said
        reg = by[(sid, "IV", "registered")]
        assert reg["status"] == "ok" and 0 <= reg["value"] <= 1 and "registered by COLMAP" in reg["note"]
        for m in ("R_err", "T_err"):
            r = by[(sid, "IV", m)]
            assert (r["status"] == "ok" and r["value"] >= 0) or (r["status"] == "failed" and r["note"])
        # VII: the fit did not run (fit.enabled is false), and it says so
        assert {by[(sid, "VII", m)]["status"] for m in ("PSNR", "SSIM", "LPIPS")} == {"unavailable"}
        assert "fit.enabled" in by[(sid, "VII", "PSNR")]["note"]


@pytest.mark.system
def test_metrics_without_weights_are_unavailable_not_invented(evaluated):
    _, _, result = evaluated
    lp = [r for r in result.rows if r["metric"] == "LPIPS" and r["table"] == "III"]
    assert lp and all(r["status"] == "unavailable" and r["value"] is None for r in lp)
    assert all(".pth" in r["note"] and "random weights" in r["note"] for r in lp)  # names the file and the rule
    dist = {r["metric"]: r for r in result.rows if r["scene_id"] is None}
    assert set(dist) == {"FID", "FVD"}
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
    assert art is not None and "Table IV" in art.data


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
    assert "of 10 frames registered" in reg["note"]  # 5 of the 9 frames of each of the 2 clips


@pytest.mark.system
def test_reference_check_detects_frames_that_do_not_match_their_cameras(evaluated, tmp_path):
    """Table III is a real comparison: frames that are not the requested views score badly."""
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
    rows = [row("III", "PSNR", 30.0, "dB", scene_id="a" * 64), row("III", "LPIPS", status="unavailable",
                                                                    note="x.pth missing", scene_id="a" * 64),
            row("III", "FID", status="unavailable", note="y missing")]
    md = evaluation_markdown("e1", rows, {"a" * 64: "room.png"}, "onnx")
    assert "SIMULATION" not in md and "| room.png `aaaaaaaaaaaa` | 30 | unavailable [1] |  |" in md
    assert "1. unavailable: x.pth missing" in md and "2. unavailable: y missing" in md


def test_cli_evaluate_refuses_a_store_without_finished_scenes(tmp_path):
    res = CliRunner().invoke(app, ["evaluate", str(tmp_path / "nope")])
    assert res.exit_code == 2 and "no navcrafter store" in res.output
    Store(str(tmp_path / "empty"))
    res = CliRunner().invoke(app, ["evaluate", str(tmp_path / "empty")])
    out = " ".join(res.output.split())
    assert res.exit_code == 2 and "no finished scenes" in out and "navcrafter explore" in out


def test_evaluate_help():
    res = CliRunner().invoke(app, ["evaluate", "--help"])
    assert res.exit_code == 0 and "Tables III-VII" in res.output.replace("\n", " ")
