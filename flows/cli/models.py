"""``navcrafter models ...``: pull the official checkpoints, export them to ONNX model directories, inspect them."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Optional

import typer

from navcrafter.flows.cli.options import run_config, usage_errors

models_app = typer.Typer(help="Download the official checkpoints (pull), export the learned models (Wan2.1 camera "
                              "control, VGGT, MoGe-2, Difix) to ONNX and inspect model directories.",
                         no_args_is_help=True)

_RANDOM = typer.Option(help="Random weights instead of a checkpoint: 'tiny' (test sizes) or 'full' (published "
                            "sizes, for timing). Outputs of runs using them are labelled RANDOM WEIGHTS.")
# what an exporter raises for a missing or wrong checkpoint, or an unsupported option
_EXPORT_ERRORS = (ValueError, FileNotFoundError, NotImplementedError)
# the clip size and prompt a synthesizer is exported for (both synthesizer models)
_Frames = Annotated[int, typer.Option(help="Frames per clip (synthesis.num_frames; 4k+1).")]
_Height = Annotated[int, typer.Option(help="synthesis.height (multiple of 16).")]
_Width = Annotated[int, typer.Option(help="synthesis.width (multiple of 16).")]
_Prompt = Annotated[str, typer.Option(help="Text prompt whose embedding is precomputed.")]


def _done(path: Path) -> None:
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.models.runtime.onnxio import load_manifest

    manifest = json.loads((Path(path) / "manifest.json").read_text())
    load_manifest(path, manifest["kind"])  # verifies what was written
    size = sum(f.stat().st_size for f in Path(path).iterdir() if f.is_file())
    typer.echo(f"exported {manifest['kind']} ({manifest['architecture']}, weights: {manifest['weights']['source']}) "
               f"to {path}: {len(manifest['graphs'])} graphs, {size / 2**20:.1f} MiB")


@models_app.command("export-geometry")
def export_geometry_cmd(
    out: Annotated[Path, typer.Argument(help="Directory to write (MODEL_DIR/geometry for `explore --models`).")],
    checkpoint: Annotated[Optional[Path], typer.Option(help="VGGT-1B weights (.safetensors, or a .pt state "
                                                             "dict loaded with weights_only).")] = None,
    random: Annotated[Optional[str], _RANDOM] = None,
    seed: int = 0,
) -> None:
    """VGGT-architecture multi-view geometry (frames -> cameras, depth, points) as ONNX."""
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.models.zoo.exporters import export_geometry

    with usage_errors(*_EXPORT_ERRORS):
        _done(export_geometry(out, checkpoint=checkpoint, random=random, seed=seed))


@models_app.command("export-monodepth")
def export_monodepth_cmd(
    out: Annotated[Path, typer.Argument(help="Directory to write (MODEL_DIR/monodepth for `explore --models`).")],
    checkpoint: Annotated[Optional[Path], typer.Option(help="MoGe-2 ViT-L weights (.safetensors, or the official "
                                                             "model.pt read with weights_only).")] = None,
    random: Annotated[Optional[str], _RANDOM] = None,
    seed: int = 0,
) -> None:
    """MoGe-2-architecture monocular geometry (image -> points, mask, metric scale) as ONNX."""
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.models.zoo.exporters import export_monodepth

    with usage_errors(*_EXPORT_ERRORS):
        _done(export_monodepth(out, checkpoint=checkpoint, random=random, seed=seed))


@models_app.command("export-refiner")
def export_refiner_cmd(
    out: Annotated[Path, typer.Argument(help="Directory to write (MODEL_DIR/refiner for `explore --models`).")],
    checkpoint: Annotated[Optional[Path], typer.Option(help="Difix weights: the nvidia/difix_ref diffusers directory "
                                                             "(unet/, vae/, text_encoder/, tokenizer/), or an official "
                                                             "training checkpoint model_*.pkl (read with "
                                                             "weights_only; needs --base).")] = None,
    base: Annotated[Optional[Path], typer.Option(help="stabilityai/sd-turbo diffusers directory: the weights a "
                                                       "training checkpoint lacks, and the text encoder for the "
                                                       "prompt.")] = None,
    prompt_embeds: Annotated[Optional[Path], typer.Option(help="Precomputed prompt embedding (.npy, [1, 77, 1024]) "
                                                                "instead of running the text encoder.")] = None,
    reference: Annotated[bool, typer.Option(help="Reference-view mixing (nvidia/difix_ref); --no-reference for "
                                                 "nvidia/difix.")] = True,
    random: Annotated[Optional[str], _RANDOM] = None,
    seed: int = 0,
) -> None:
    """Difix-architecture single-step diffusion refiner (render + reference view -> refined view) as ONNX."""
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.models.zoo.exporters import export_refiner

    with usage_errors(*_EXPORT_ERRORS):
        _done(export_refiner(out, checkpoint=checkpoint, random=random, seed=seed, base=base,
                             prompt_embeds=prompt_embeds, reference=reference))


@models_app.command("export-synthesizer")
def export_synthesizer_cmd(
    out: Annotated[Path, typer.Argument(help="Directory to write (MODEL_DIR/synthesizer for `explore --models`).")],
    base: Annotated[Optional[Path], typer.Option(help="Diffusers-format Wan2.1 I2V directory (transformer/, vae/, "
                                                       "image_encoder/, text_encoder/, tokenizer/).")] = None,
    control: Annotated[Optional[Path], typer.Option(help="Camera-control weights directory (safetensors + "
                                                          "config.json); none: zero-initialised control.")] = None,
    random: Annotated[Optional[str], _RANDOM] = None,
    frames: _Frames = 81,
    height: _Height = 256,
    width: _Width = 256,
    prompt: _Prompt = "",
    seed: int = 0,
) -> None:
    """Camera-controlled Wan2.1 I2V (DiT, VAE encoder/decoder, image encoder, text embeddings) as ONNX."""
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.models.zoo.exporters import export_synthesizer

    with usage_errors(*_EXPORT_ERRORS):
        _done(export_synthesizer(out, num_frames=frames, height=height, width=width, base_dir=base,
                                 control_dir=control, random=random, prompt=prompt, seed=seed))


@models_app.command("export-fun-camera")
def export_fun_camera_cmd(
    out: Annotated[Path, typer.Argument(help="Directory to write (MODEL_DIR/synthesizer; run with "
                                             "--set synthesis.model=fun-camera).")],
    checkpoint: Annotated[Optional[Path], typer.Option(help="The official Wan2.1-Fun-V1.1-*-Control-Camera folder "
                                                             "(config.json + diffusion_pytorch_model*.safetensors).")
                          ] = None,
    base: Annotated[Optional[Path], typer.Option(help="Diffusers-format Wan2.1 I2V directory for the VAE, CLIP image "
                                                       "encoder and text encoder (with --checkpoint).")] = None,
    random: Annotated[Optional[str], typer.Option(help="'tiny': tiny random weights (tests); outputs of runs using "
                                                       "them are labelled RANDOM WEIGHTS.")] = None,
    frames: _Frames = 81,
    height: _Height = 256,
    width: _Width = 256,
    prompt: _Prompt = "",
    seed: int = 0,
) -> None:
    """The public camera-controlled Wan2.1-Fun-V1.1 Control-Camera (synthesis.model=fun-camera) as ONNX."""
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.models.zoo.exporters import export_fun_camera

    with usage_errors(*_EXPORT_ERRORS):
        _done(export_fun_camera(out, checkpoint_dir=checkpoint, base_dir=base, random=random, num_frames=frames,
                                height=height, width=width, prompt=prompt, seed=seed))


@models_app.command("convert-fp16")
def convert_fp16_cmd(
    directory: Annotated[Path, typer.Argument(help="An exported model directory (e.g. MODEL_DIR/synthesizer).")],
    graph: Annotated[Optional[list[str]], typer.Option(
        "--graph", help="Graph to convert (repeatable; default: dit, the video DiT).")] = None,
) -> None:
    """Convert graphs of a model directory to fp16 in place (normalisations and inputs/outputs stay fp32): half the
    memory and fp16 kernels on the CUDA execution provider; on the CPU it runs, slower."""
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.models.runtime.onnxio import ModelDirError, convert_model_dir_fp16

    with usage_errors(ModelDirError, *_EXPORT_ERRORS):
        manifest = convert_model_dir_fp16(directory, tuple(graph or ("dit",)))
    typer.echo(f"{directory}: " + ", ".join(f"{g} {p}" for g, p in manifest["precision"].items()))


@models_app.command("export-all")
def export_all_cmd(
    model_dir: Annotated[Path, typer.Argument(help="MODEL_DIR for `explore --backend onnx --models MODEL_DIR`.")],
    random: Annotated[str, _RANDOM] = "tiny",
    preset: Annotated[str, typer.Option(help="Run preset whose synthesis sizes the synthesizer is exported "
                                             "for: 'paper' or 'tiny'.")] = "tiny",
    seed: int = 0,
) -> None:
    """All three models with random weights (tests, demos of the onnx path, timing)."""
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.models.zoo.exporters import export_all

    s = run_config(preset).synthesis
    with usage_errors(*_EXPORT_ERRORS):
        for path in export_all(model_dir, num_frames=s.num_frames, height=s.height, width=s.width, random=random,
                               seed=seed).values():
            _done(path)


@models_app.command("show")
def show_cmd(
    model_dir: Annotated[Path, typer.Argument(help="A model directory (or MODEL_DIR holding the three roles).")],
    verify: Annotated[bool, typer.Option(help="Check every file's sha256.")] = True,
) -> None:
    """What a model directory holds, with checksum verification."""
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.models.runtime.onnxio import ModelDirError, load_manifest
    from navcrafter.models.zoo.modeldir import ROLE_DIRS

    dirs = [model_dir] if (model_dir / "manifest.json").is_file() else [model_dir / d for d in ROLE_DIRS.values()]
    for d in dirs:
        if not (d / "manifest.json").is_file():
            typer.echo(f"{d}: missing")
            continue
        kind = json.loads((d / "manifest.json").read_text())["kind"]
        with usage_errors(ModelDirError):
            m = load_manifest(d, kind, verify=verify)
        typer.echo(f"{d}: {kind} {m['architecture']}, weights {m['weights']['source']}, graphs "
                   f"{', '.join(m['graphs'])}, {len(m['files'])} files" + (" (checksums ok)" if verify else ""))


@models_app.command("pull")
def pull_cmd(
    role: Annotated[Optional[list[str]], typer.Option(
        "--role", help="Role to pull (repeatable): synthesizer (Wan2.1 I2V 14B base), fun-camera (Wan2.1-Fun 1.3B "
                       "Control-Camera), geometry (VGGT-1B), monodepth (MoGe-2 ViT-L), refiner (Difix), eval "
                       "(LPIPS/FID/FVD networks). Default: geometry, monodepth, fun-camera.")] = None,
    cache: Annotated[Optional[Path], typer.Option(help="Hugging Face hub cache to download into (default: "
                                                       "huggingface_hub's, $HF_HUB_CACHE).")] = None,
    out: Annotated[Optional[Path], typer.Option(help="MODEL_DIR to export into (for `explore --backend onnx "
                                                     "--models MODEL_DIR`).")] = None,
    offline: Annotated[bool, typer.Option(help="No network: use only the cache, verified against the record an "
                                               "earlier pull wrote (HF_HUB_OFFLINE=1 does the same).")] = False,
    export: Annotated[bool, typer.Option(help="Export into --out after verifying (--no-export: download and "
                                              "verify only).")] = True,
    revision: Annotated[Optional[str], typer.Option(help="Branch, tag or commit of the repositories (default "
                                                         "main).")] = None,
    preset: Annotated[str, typer.Option(help="Run preset whose synthesis sizes the synthesizer is exported for: "
                                             "'paper' or 'tiny'.")] = "paper",
) -> None:
    """Download the official checkpoints with huggingface_hub, verify their sizes and sha256, export them."""
    # deferred: CLI start-up (`navcrafter --help` imports no command's dependencies)
    from navcrafter.models.zoo.hub import HubError, pull

    s = run_config(preset).synthesis
    with usage_errors(HubError):
        results = pull(role, cache, out, local_files_only=offline, export=export, revision=revision,
                       num_frames=s.num_frames, height=s.height, width=s.width, log=typer.echo)
    for r in results:
        for note in r.notes:
            typer.echo(f"{r.role}: {note}")
        if r.exported is not None:
            if (r.exported / "manifest.json").is_file():
                _done(r.exported)
            else:
                typer.echo(f"{r.role}: copied {r.files} files into {r.exported} (pass it as --eval-weights)")
