"""What the ``navcrafter`` commands share: the consoles, the exit codes, the config options (declared here once)
and the one way a user's mistake ends a command: its message and the usage exit code, never a traceback."""

from __future__ import annotations

import difflib
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, NoReturn, Optional

import typer
import yaml
from rich.console import Console
from rich.markup import escape

if TYPE_CHECKING:
    from pydantic import BaseModel, ValidationError

    from navcrafter.schemas.config import RunConfig

# Wide when piped (logs, CI): rich would otherwise fold the summary table into 80 columns.
console = Console(width=None if sys.stdout.isatty() else 160)
err = Console(stderr=True, width=None if sys.stderr.isatty() else 160)

EXIT_USAGE = 2
EXIT_PARTIAL = 3

# The config options of every command that builds a RunConfig (explore, evaluate, submit); see run_config.
PresetOption = Annotated[str, typer.Option("--preset", help="Config preset: 'paper' (defaults of the paper) or "
                                                              "'tiny'.")]
ConfigOption = Annotated[Optional[Path], typer.Option("--config", help="YAML/JSON config file applied over the "
                                                                        "preset.")]
SetOption = Annotated[Optional[list[str]], typer.Option("--set", help="Override, e.g. --set lift.max_views=8.")]


def prefect_env() -> None:
    """Offline-friendly Prefect defaults (each can be overridden from the environment)."""
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("PREFECT_LOGGING_EXTRA_LOGGERS", "navcrafter")
    # The temporary local server needs longer than Prefect's 20 s default on a busy 2-core machine.
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "90")


def fail(*lines: str) -> NoReturn:
    """End the command on a user's mistake: each line in red on stderr (plain text, never read as markup, never
    wrapped, so that one problem stays one line in a log), then the usage exit code."""
    for line in lines:
        err.print(f"[red]{escape(line)}[/red]", soft_wrap=True)
    raise typer.Exit(EXIT_USAGE)


@contextmanager
def usage_errors(*expected: type[Exception]) -> Iterator[None]:
    """The ``expected`` errors of the block (a missing store, a bad dataset folder, ...) are the user's to fix:
    they end the command through ``fail`` with their own message."""
    try:
        yield
    except expected as exc:
        fail(str(exc))


def run_config(preset: str = "paper", config: Path | None = None, sets: list[str] | None = None,
               overrides: dict[str, Any] | None = None) -> RunConfig:
    """The RunConfig of a command: the preset, then the --config file, then the --set overrides, then the
    command's own options (``overrides``, dotted keys; None values are left out). A mistake in any of them ends
    the command here, before any work starts, with one line per mistake."""
    from pydantic import ValidationError

    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.schemas.config import RunConfig

    merged = {**_parse_sets(sets or []), **{k: v for k, v in (overrides or {}).items() if v is not None}}
    try:
        return RunConfig.load(config, preset=preset, overrides=merged)
    except ValidationError as exc:
        fail(*(f"invalid configuration: {line}" for line in _validation_lines(exc, RunConfig)))
    except yaml.YAMLError as exc:  # only the file can hold it: the --set values were parsed above
        fail(f"invalid configuration: config file {config} is not valid YAML/JSON ({_yaml_problem(exc)})")
    except (ValueError, FileNotFoundError) as exc:  # an unknown preset, a missing file, a file that is no mapping
        fail(f"invalid configuration: {exc}")


def _parse_sets(values: list[str]) -> dict[str, Any]:
    """``--set KEY=VALUE`` options as dotted overrides; each VALUE is read as YAML (so JSON too: 9, true, [1, 2])."""
    out = {}
    for item in values:
        if "=" not in item:
            raise typer.BadParameter(f"--set expects KEY=VALUE (e.g. synthesis.num_frames=9), got {item!r}")
        key, value = item.split("=", 1)
        try:
            out[key.strip()] = yaml.safe_load(value)
        except yaml.YAMLError as exc:
            raise typer.BadParameter(f"--set {item!r}: the value is not valid YAML/JSON ({_yaml_problem(exc)})"
                                     ) from None
    return out


def _yaml_problem(exc: yaml.YAMLError) -> str:
    """The parser's own words and where, without the excerpt of the input it prints over several lines."""
    problem = getattr(exc, "problem", None) or str(exc)
    mark = getattr(exc, "problem_mark", None)
    return f"{problem} at line {mark.line + 1}, column {mark.column + 1}" if mark else problem


def _validation_lines(exc: ValidationError, model: type[BaseModel]) -> list[str]:
    """One line per error of a validation of ``model``: the dotted field, then the problem (pydantic's own text
    takes three lines per error, one of them a link to its documentation)."""
    lines = []
    for e in exc.errors():
        field = ".".join(str(part) for part in e["loc"])
        if e["type"] == "extra_forbidden":
            lines.append(_unknown_key(model, e["loc"]))
            continue
        # a validator's own message already names its fields and values; a missing field has none to show
        msg = e["msg"].removeprefix("Value error, ")
        if e["type"] not in ("value_error", "missing"):
            msg += f" (got {e['input']!r})"
        lines.append(f"{field}: {msg}" if field and not msg.startswith(field) else msg)
    return lines


def _unknown_key(model: type[BaseModel], loc: tuple[int | str, ...]) -> str:
    """``loc`` names no field of its section: say so, with the closest field and every valid key there."""
    from pydantic import BaseModel

    dotted = ".".join(str(part) for part in loc)
    section = model
    for part in loc[:-1]:
        info = section.model_fields.get(part) if isinstance(part, str) else None
        if info is None or not (isinstance(info.annotation, type) and issubclass(info.annotation, BaseModel)):
            return f"{dotted}: unknown key"
        section = info.annotation
    names = list(section.model_fields)
    parent = ".".join(str(part) for part in loc[:-1])
    close = difflib.get_close_matches(str(loc[-1]), names, n=1)
    hint = f" (did you mean {parent + '.' if parent else ''}{close[0]}?)" if close else ""
    return (f"{dotted}: unknown key{hint}; valid keys {'of ' + parent if parent else 'at the top level'}: "
            f"{', '.join(names)}")
