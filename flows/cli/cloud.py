"""``navcrafter evaluate-cloud``: a point cloud (or mesh) against a reference cloud (or mesh): precision, recall,
F-score, Coverage and Noise ratio at a distance threshold, optionally after ICP alignment
(``flows.tools.interchange.evaluate_cloud_files``; the definitions: ``models.metrics.cloud``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from navcrafter.flows.cli.options import console, fail, usage_errors

ROWS = (("precision", "Precision"), ("recall", "Recall"), ("fscore", "F-score"), ("coverage", "Coverage"),
        ("noise_ratio", "Noise ratio"), ("median_dist_to_reference", "median pred->GT"),
        ("median_dist_from_reference", "median GT->pred"))


def evaluate_cloud(
    pred: Annotated[Path, typer.Argument(help="Predicted cloud (.ply, .pcd, .xyz, ...; a mesh is sampled).")],
    gt: Annotated[Path, typer.Argument(help="Reference cloud, or a mesh (sampled uniformly).")],
    threshold: Annotated[float, typer.Option(help="Distance threshold, in the files' units (paper: 2 cm).")] = 0.02,
    align: Annotated[bool, typer.Option(
        "--align/--no-align", help="Also score after Open3D point-to-point ICP of PRED onto GT (identity start).")
    ] = False,
    icp_distance: Annotated[Optional[float], typer.Option(
        help="ICP max correspondence distance (default: 5 x --threshold).")] = None,
    mesh_points: Annotated[int, typer.Option(min=1, help="Points sampled on a mesh file.")] = 1_000_000,
    out: Annotated[Optional[Path], typer.Option("--out", help="Write the results as JSON to this file.")] = None,
) -> None:
    """Score a point cloud against a reference: precision, recall, F-score, Coverage, Noise ratio."""
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.flows.tools.interchange import InterchangeError, evaluate_cloud_files

    with usage_errors(InterchangeError):
        doc = evaluate_cloud_files(pred, gt, threshold, align, icp_distance, mesh_points)
    table = Table(title=f"{pred.name} vs {gt.name} at {threshold:g}")
    table.add_column("metric")
    table.add_column("unaligned", justify="right")
    if align:
        table.add_column("ICP-aligned", justify="right")
    for key, name in ROWS:
        table.add_row(name, *(f"{doc[part][key]:.4f}" for part in ("unaligned", "aligned") if part in doc))
    console.print(table)
    mesh = [f"{w.upper()} is a mesh, sampled uniformly" for w in ("pred", "gt") if doc[f"{w}_sampled_from_mesh"]]
    console.print("; ".join([f"{doc['n_pred']} predicted, {doc['n_gt']} reference points", *mesh]))
    if align:
        a = doc["aligned"]
        console.print(f"ICP (max correspondence {a['icp']['max_correspondence_distance']:g}): fitness "
                      f"{a['icp']['fitness']:.3f}, inlier RMSE {a['icp']['inlier_rmse']:.4g}; transform")
        for row in a["transform"]:
            console.print("  " + " ".join(f"{v: .6f}" for v in row))
    if out is not None:
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(json.dumps(doc, indent=1))
        except OSError as exc:
            fail(f"cannot write {out}: {exc}")
        console.print(f"-> {out}")
