from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from navcrafter.flows.cli import app

runner = CliRunner()


@pytest.mark.parametrize("cmd", [[], ["demo-data"], ["explore"], ["status"]])
def test_help(cmd):
    res = runner.invoke(app, [*cmd, "--help"])
    assert res.exit_code == 0, res.output
    assert "Usage" in res.output


def test_usage_errors_are_clear(tmp_path):
    res = runner.invoke(app, ["status", str(tmp_path / "nope")])
    assert res.exit_code == 2 and "no navcrafter store" in res.output
    res = runner.invoke(app, ["explore", str(tmp_path), "--store", str(tmp_path / "s"), "--backend", "onnx",
                              "--models", str(tmp_path)])
    assert res.exit_code == 2 and "not an exported synthesizer model directory" in res.output, res.output
    res = runner.invoke(app, ["explore", str(tmp_path), "--store", str(tmp_path / "s"), "--set", "fit.enabled=true",
                              "--set", "iterations=0"])
    assert res.exit_code == 2 and "fit.enabled needs iterations" in res.output, res.output
    assert not (tmp_path / "s").exists()  # refused before any work
    res = runner.invoke(app, ["explore", str(tmp_path), "--store", str(tmp_path / "s"), "--set", "iterations"])
    assert res.exit_code == 2 and "KEY=VALUE" in res.output
    res = runner.invoke(app, ["explore", str(tmp_path), "--store", str(tmp_path / "s"), "--set", "iterations=-1"])
    assert res.exit_code == 2 and "invalid configuration" in res.output
    res = runner.invoke(app, ["explore", str(tmp_path / "missing"), "--store", str(tmp_path / "s")])
    assert res.exit_code == 2 and "demo-data" in res.output
    res = runner.invoke(app, ["demo-data", str(tmp_path / "d"), "--kinds", "castle"])
    assert res.exit_code == 2 and "unknown scene kind" in res.output


def test_status_shows_manifest(full_run):
    store = full_run[0]
    res = runner.invoke(app, ["status", str(store)], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    assert "room-0.png" in res.output and "done" in res.output and "failed" in res.output
    assert "SIMULATION MODE" in res.output
    res = runner.invoke(app, ["status", str(store), "--json", "--compact"])
    rows = [json.loads(line) for line in res.output.strip().splitlines()]
    assert {r["status"] for r in rows} == {"done", "failed"}
