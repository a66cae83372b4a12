"""Run configuration: one pydantic model per pipeline step, with the paper's defaults.

Every number that changes a stored output lives here, so that a step's cache key can be derived from
the part of the config it reads (``RunConfig.step_config``). Defaults follow the NavCrafter paper
(N=3 iterations, K=3 candidates, 81-frame clips at 256x256, DPM-solver 40 steps, CFG 6.5, LoRA weight
0.7); the ``tiny`` preset shrinks sizes for tests and quick looks.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

# Each model package owns its settings beside its code; the run configuration composes them (re-exported here)
from navcrafter.models.gaussians.config import LOSS_WEIGHTINGS, FitConfig, RefineConfig
from navcrafter.models.metrics.config import EvaluationConfig
from navcrafter.models.planning.config import PlanConfig
from navcrafter.models.reconstruction.config import LiftConfig
from navcrafter.models.settings import Section as _Section
from navcrafter.models.simulation.config import SimulationConfig
from navcrafter.models.synthesis.config import SynthesisConfig
from navcrafter.schemas.keys import stable_hash, step_config
from navcrafter.schemas.layout import STEPS

Backend = Literal["simulation", "onnx"]


__all__ = ["LOSS_WEIGHTINGS", "Backend", "EvaluationConfig", "FitConfig", "IngestConfig", "LiftConfig", "PlanConfig",
           "PRESETS", "RefineConfig", "RunConfig", "SimulationConfig", "SynthesisConfig"]


class IngestConfig(_Section):
    """Validation and normalisation of input photos."""

    max_file_bytes: int = Field(64 * 2**20, gt=0, description="Reject files larger than this.")
    max_pixels: int = Field(
        100_000_000, gt=0, description="Reject images with more pixels (decompression-bomb guard)."
    )
    min_side: int = Field(64, gt=0, description="Reject images whose shorter side is smaller.")
    max_side: int = Field(
        1024, gt=0, description="The stored normalised input is downscaled to this longer side."
    )
    alpha_background: tuple[int, int, int] = Field(
        (255, 255, 255), description="Colour that transparent pixels are composited onto."
    )


class RunConfig(BaseModel):
    """Everything a run needs besides its inputs and its store."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    backend: Backend = Field(
        "simulation",
        description="'simulation' renders procedural ground truth in place of learned models; "
        "'onnx' runs exported models from model_dir.",
    )
    model_dir: Path | None = Field(None, description="Directory of exported ONNX models (onnx backend).")
    iterations: int = Field(3, ge=0, description="N: plan/synthesize/lift iterations (paper: 3).")
    seed: int = Field(0, description="Base seed; each step derives its own from scene, step and config.")
    max_parallel_scenes: int = Field(2, ge=1, description="Scenes processed at once in one process.")
    gpu_limit: str | None = Field(
        None,
        description="Name of a Prefect global concurrency limit (`prefect gcl create NAME --limit GPUs`) "
        "of which each model-running step (geometry, synthesize, lift, fit) occupies one slot; "
        "None: unbounded, and no API call per step.",
    )
    release_models: bool = Field(
        True, description="onnx backend: release a step's models (their onnxruntime sessions) when it ends, so a "
        "process holds one step's models at a time (a 24 GB GPU holds one role at a time; reloading costs seconds "
        "per step); False keeps every loaded role for the process (faster on a large GPU, more memory).")
    ingest: IngestConfig = IngestConfig()
    synthesis: SynthesisConfig = SynthesisConfig()
    plan: PlanConfig = PlanConfig()
    lift: LiftConfig = LiftConfig()
    fit: FitConfig = FitConfig()
    refine: RefineConfig = RefineConfig()
    simulation: SimulationConfig = SimulationConfig()
    evaluation: EvaluationConfig = EvaluationConfig()

    @field_validator("model_dir")
    @classmethod
    def _expand(cls, v: Path | None) -> Path | None:
        return None if v is None else Path(v).expanduser()

    # fields that change no stored output (scheduling only): the only ones that key no step
    # (tests/schemas/test_cache_keys.py checks every other field keys some step)
    NOT_KEYING: ClassVar[dict[str, str]] = {
        "max_parallel_scenes": "how many scenes run at once", "gpu_limit": "which concurrency limit steps wait on",
        "fit.threads": "the compiled rasterizer's threads (its results do not depend on them)",
        "release_models": "when loaded models are freed (outputs do not depend on it)",
        "synthesis.offload": "whether the synthesizer's graphs are held one at a time (the frames do not change)"}

    @model_validator(mode="after")
    def _check(self) -> RunConfig:
        """Every rule between sections, in one place (checked whenever a config is made or loaded)."""
        problems = []
        if self.backend == "onnx" and self.model_dir is None:
            problems.append("backend 'onnx' needs model_dir, a directory of exported ONNX models: pass "
                            "`--models DIR` (or model_dir in the config file); `navcrafter models export-all DIR` "
                            "writes one (random weights), `navcrafter models export-synthesizer/-geometry/"
                            "-monodepth/-refiner` export each model")
        if self.fit.enabled and self.iterations < 1:
            problems.append("fit.enabled needs iterations >= 1: the Gaussians are fitted to the synthesized frames")
        if self.refine.enabled and not self.fit.enabled:
            problems.append("refine.enabled needs fit.enabled: the refine step starts from the fitted Gaussians")
        if problems:
            raise ValueError("; ".join(problems))
        return self

    # -- hashing ---------------------------------------------------------------------------------
    def step_config(self, step: str) -> dict[str, Any]:
        """The part of the config that a step's output depends on (``schemas.keys.step_config``)."""
        if step not in STEPS:
            raise KeyError(f"unknown step {step!r}; known: {sorted(STEPS)}")
        return step_config(STEPS[step], self)

    def config_hash(self) -> str:
        return stable_hash(self.model_dump(mode="json"))

    # -- loading ---------------------------------------------------------------------------------
    @classmethod
    def load(cls, path: str | Path | None = None, preset: str = "paper",
             overrides: dict[str, Any] | None = None) -> RunConfig:
        """Preset, then a YAML/JSON file, then dotted overrides (``{"synthesis.num_frames": 9}``)."""
        data = PRESETS[preset]() if preset in PRESETS else _unknown_preset(preset)
        if path is not None:
            p = Path(path)
            if not p.is_file():
                raise FileNotFoundError(f"config file {p} does not exist")
            loaded = yaml.safe_load(p.read_text()) or {}
            if not isinstance(loaded, dict):
                raise ValueError(f"config file {p} must hold a mapping, got {type(loaded).__name__}")
            data = _deep_merge(data, loaded)
        for dotted, value in (overrides or {}).items():
            data = _deep_merge(data, _dotted_to_nested(dotted, value))
        return cls.model_validate(data)


def _paper() -> dict[str, Any]:
    return {}


def _tiny() -> dict[str, Any]:
    return {
        "iterations": 2,
        "synthesis": {"num_frames": 9, "height": 64, "width": 64},
        "lift": {"max_views": 4, "pixel_stride": 1, "voxel_size": 0.03},
        "fit": {"enabled": False, "iterations": 40, "resolution": 32, "max_init_points": 3000, "sh_degree": 1,
                "sh_degree_interval": 20, "lr_means": 1.6e-3, "lr_means_final": 1.6e-4, "densify_start": 10,
                "densify_every": 10, "densify_stop": 30, "reset_every": 0, "max_gaussians": 4000},
    }


PRESETS = {"paper": _paper, "tiny": _tiny}


def _unknown_preset(name: str) -> dict[str, Any]:
    raise ValueError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")


def _deep_merge(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    out = dict(a)
    for k, v in b.items():
        out[k] = _deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _dotted_to_nested(dotted: str, value: Any) -> dict[str, Any]:
    keys = dotted.split(".")
    nested: dict[str, Any] = {keys[-1]: value}
    for k in reversed(keys[:-1]):
        nested = {k: nested}
    return nested


# -- the run configuration stored with each scene ------------------------------------------------------------------
RUN_CONFIG_FILE = "run_config.json"  # scenes/<scene_id>/run_config.json (schemas.layout.scene_group)
RUN_CONFIG_FORMAT = "navcrafter-run-config"
RUN_CONFIG_HISTORY = 20  # the last runs' config hashes kept beside the latest config


class StoredRunConfig(BaseModel):
    """What a scene run stores before its first step: the resolved ``RunConfig`` it runs with.

    Written at the start of every run of the scene (``tasks.runner.record_run_config``), so it is the latest run's
    config: every step that run completed was skipped (its cache key, hence the config part it reads, unchanged) or
    recomputed with it. ``history`` lists the earlier runs' config hashes (newest last): a scene resumed with a
    different config says so. Tools that read a finished scene (render, view, export) take the config from here.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    format: Literal["navcrafter-run-config"] = RUN_CONFIG_FORMAT
    version: int = 1
    scene_id: str
    run_id: str
    written_at: str
    config_hash: str
    config: RunConfig
    history: list[dict[str, str]] = Field(default_factory=list, description="earlier runs: run_id, config_hash, "
                                          "written_at (newest last, at most RUN_CONFIG_HISTORY)")
