from __future__ import annotations

import json
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from navcrafter.flows.cli import app

runner = CliRunner()


@pytest.mark.parametrize("cmd", [[], ["demo-data"], ["explore"], ["status"]])
def test_help(cmd):
    res = runner.invoke(app, [*cmd, "--help"])
    assert res.exit_code == 0, res.output
    assert "Usage" in res.output


HEAVY = ("torch", "open3d", "onnxruntime", "prefect", "viser", "pycolmap", "diffusers", "scipy", "zarr")


@pytest.mark.subprocess
def test_help_loads_no_heavy_dependency():
    """`navcrafter --help` and a command's --help start light: the commands' imports are deferred (`# deferred: CLI
    start-up` in flows/cli/). A fresh interpreter, since this session has long imported torch."""
    code = ("import json, sys\nfrom navcrafter.flows.cli import main\n"
            "for argv in (['--help'], ['explore', '--help'], ['render', '--help'], ['models', '--help']):\n"
            "    sys.argv = ['navcrafter', *argv]\n"
            "    try:\n        main()\n    except SystemExit:\n        pass\n"
            "print(json.dumps(sorted({m.split('.')[0] for m in sys.modules})))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    loaded = set(json.loads(p.stdout.strip().splitlines()[-1]))
    assert "typer" in loaded  # the check sees what was imported
    assert not loaded & set(HEAVY), sorted(loaded & set(HEAVY))


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


def _lines(res):
    return [line for line in res.output.splitlines() if line.strip()]


def test_config_mistakes_are_one_line_each(tmp_path):
    """A config mistake names the dotted field and the problem on one line (pydantic's own text spans three lines
    per error and links to its docs), exits with the usage code and writes nothing."""
    base = ["explore", str(tmp_path), "--store", str(tmp_path / "s")]
    res = runner.invoke(app, [*base, "--set", "fit.iteratons=5"])  # mistyped: the key and the section's keys
    assert res.exit_code == 2, res.output
    [line] = _lines(res)
    assert line.startswith("invalid configuration: fit.iteratons: unknown key (did you mean fit.iterations?)")
    assert "valid keys of fit: enabled, iterations, " in line
    res = runner.invoke(app, [*base, "--set", "itrations=5"])
    assert res.exit_code == 2 and "did you mean iterations?" in res.output
    assert "valid keys at the top level: backend, model_dir, iterations, " in res.output
    res = runner.invoke(app, [*base, "--set", "fit.iterations=0", "--set", "lift.max_views=0"])  # out of range
    assert res.exit_code == 2
    assert _lines(res) == ["invalid configuration: lift.max_views: Input should be greater than or equal to 1 (got 0)",
                           "invalid configuration: fit.iterations: Input should be greater than or equal to 1 (got 0)"]
    res = runner.invoke(app, [*base, "--backend", "onnx"])  # a rule between fields: the validator's own words
    assert res.exit_code == 2 and "Value error" not in res.output and "errors.pydantic.dev" not in res.output
    [line] = _lines(res)
    assert line.startswith("invalid configuration: backend 'onnx' needs model_dir")
    res = runner.invoke(app, [*base, "--set", "synthesis.num_frames=[9,"], env={"COLUMNS": "200"})  # one panel line
    assert res.exit_code == 2 and "not valid YAML/JSON" in res.output and "KEY=VALUE" not in res.output
    (tmp_path / "run.yaml").write_text("lift: [1,\n")
    res = runner.invoke(app, [*base, "--config", str(tmp_path / "run.yaml")])
    assert res.exit_code == 2 and "run.yaml is not valid YAML/JSON" in res.output
    assert res.exception is None or isinstance(res.exception, SystemExit)  # no traceback
    (tmp_path / "run.yaml").write_text("lift:\n  max_veiws: 3\n")
    res = runner.invoke(app, ["evaluate", str(tmp_path / "s"), "--config", str(tmp_path / "run.yaml")])
    assert res.exit_code == 2 and "lift.max_veiws: unknown key (did you mean lift.max_views?)" in res.output
    res = runner.invoke(app, ["submit", str(tmp_path), "--store", str(tmp_path / "s"), "--set", "seed=x"])
    assert res.exit_code == 2 and "seed: Input should be a valid integer" in res.output and "(got 'x')" in res.output
    res = runner.invoke(app, ["models", "export-all", str(tmp_path / "m"), "--preset", "huge"])
    assert res.exit_code == 2 and "unknown preset 'huge'" in res.output
    assert not (tmp_path / "s").exists() and not (tmp_path / "m").exists()  # refused before any work


@pytest.mark.system
def test_status_shows_manifest(full_run):
    store = full_run[0]
    res = runner.invoke(app, ["status", str(store)], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    assert "room-0.png" in res.output and "done" in res.output and "failed" in res.output
    assert "SIMULATION MODE" in res.output
    res = runner.invoke(app, ["status", str(store), "--json", "--compact"])
    rows = [json.loads(line) for line in res.output.strip().splitlines()]
    assert {r["status"] for r in rows} == {"done", "failed"}
