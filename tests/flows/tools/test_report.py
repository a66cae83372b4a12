"""flows/tools/report.py: the scene summary (``scene_summary``) that the run summary's rows (``scene_result``) and
the scene dashboard render, on a scene written straight into a store (the flows' own tests run it end to end)."""

from __future__ import annotations

from render_fixtures import blob_model, write_scene

from navcrafter.flows.tools.report import scene_result, scene_summary
from navcrafter.models.simulation import LABEL as SIM_LABEL
from navcrafter.schemas.config import RunConfig
from navcrafter.schemas.store import Store


def test_scene_summary_reads_steps_timings_and_the_final_gaussians(tmp_path):
    write_scene(tmp_path / "store", "ab" * 32, blob_model(n=20, degree=0))  # ingest, plan of iteration 1, fit
    scene = Store(str(tmp_path / "store")).scene("ab" * 32)
    cfg = RunConfig(iterations=1).model_copy(update={"fit": RunConfig().fit.model_copy(update={"enabled": True})})
    s = scene_summary(scene, cfg)
    assert s.last_step is None  # the geometry step (the run's first; ingest is the collection's) is missing
    assert (s.done, s.steps) == (2, 6)  # the plan of iteration 1 and the fit, of geometry ... exports
    assert list(s.timings) == ["iter_1/plan", "gaussians"] and not s.evaluated and s.evaluation == {}
    assert s.gaussians == {"gs_psnr": 0.0, "gs_gaussians": 20.0} and s.label == SIM_LABEL
    assert scene_summary(scene, cfg, "RANDOM WEIGHTS").label == "RANDOM WEIGHTS"  # a label the caller read
    no_fit = cfg.model_copy(update={"fit": cfg.fit.model_copy(update={"enabled": False})})
    assert scene_summary(scene, no_fit).gaussians == {}  # a run that does not fit reports no Gaussians
    r = scene_result(scene, ["x.png"], cfg, "failed", metrics={"n_points": 5.0})
    assert (r.step, r.seconds, r.label) == (None, 0.0, SIM_LABEL)
    assert r.metrics == {"n_points": 5.0, "gs_psnr": 0.0, "gs_gaussians": 20.0}


def test_summary_rows_show_what_was_seen_and_the_5cm_coverage():
    from navcrafter.flows.tools.report import SUMMARY_COLUMNS, SceneResult, summary_rows

    r = SceneResult("abc", ["photos/room-0.png"], "done",
                    metrics={"seen": 0.381, "coverage": 0.25, "coverage_at_0.05": 0.412, "collisions": 6})
    (row,) = summary_rows([r])
    assert len(row) == len(SUMMARY_COLUMNS)
    cell = dict(zip(SUMMARY_COLUMNS, row))
    assert cell["seen"] == "0.381" and cell["coverage 5 cm"] == "0.412" and cell["coverage"] == "0.250"
    assert cell["collisions"] == "6"
