"""Export commands' implementation: one function per role plus ``export_all`` (used by the CLI and tests).

``random`` presets build the architecture with random weights: ``"tiny"`` (test configs, seconds) or
``"full"`` (the published sizes, for timing). Their manifests say ``weights.source = "random"`` and every
output of a run that uses them is labelled ``RANDOM_WEIGHTS_LABEL``. Real weights come from files the user
has (``checkpoint`` / ``base_dir``): safetensors (or torch state dicts read with ``weights_only=True``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from navcrafter.models.geometry import moge
from navcrafter.models.refiner import difix
from navcrafter.models.synthesis import onnx_export
from navcrafter.models.zoo.modeldir import role_dir

RandomPreset = Literal["tiny", "full"]


def _need_source(role: str, random: str | None, source) -> None:
    if (random is None) == (source is None):
        flag = "--base" if role == "synthesizer" else "--checkpoint"
        raise ValueError(f"export-{role}: give either the weights ({flag}) or --random tiny|full "
                         f"(random weights, for tests and timing)")


def export_geometry(out: Path, *, checkpoint: Path | None = None, random: RandomPreset | None = None,
                    seed: int = 0) -> Path:
    # deferred: VGGT's modules load transformers and scipy only when a geometry model is exported
    from navcrafter.models.geometry.vggt import VGGTConfig
    from navcrafter.models.geometry.vggt import export_geometry as _export

    _need_source("geometry", random, checkpoint)
    config = VGGTConfig.tiny() if random == "tiny" else VGGTConfig.vggt_1b()
    return _export(Path(out), config, weights=checkpoint, seed=seed)


def export_monodepth(out: Path, *, checkpoint: Path | None = None, random: RandomPreset | None = None,
                     seed: int = 0) -> Path:
    _need_source("monodepth", random, checkpoint)
    config = moge.MoGe2Config.tiny() if random == "tiny" else moge.MoGe2Config.vitl_normal()
    return moge.export_monodepth(Path(out), config, weights=checkpoint, seed=seed)


def export_refiner(out: Path, *, checkpoint: Path | None = None, random: RandomPreset | None = None, seed: int = 0,
                   base: Path | None = None, prompt_embeds: Path | None = None, reference: bool = True) -> Path:
    """Difix refiner (``models/refiner/difix/``). ``checkpoint``: the ``nvidia/difix_ref`` diffusers directory
    (or ``nvidia/difix`` with ``reference=False``), or an official training checkpoint ``model_*.pkl`` with
    ``base`` = the ``stabilityai/sd-turbo`` directory; the prompt embedding comes from the text encoder found
    there unless ``prompt_embeds`` (.npy) is given."""
    _need_source("refiner", random, checkpoint)
    if random is not None and (base is not None or prompt_embeds is not None):
        raise ValueError("export-refiner: --base and --prompt-embeds go with --checkpoint, not --random")
    config = difix.DifixConfig.tiny(reference) if random == "tiny" else difix.DifixConfig.sd_turbo(reference)
    return difix.export_refiner(Path(out), config, weights=checkpoint, seed=seed, base=base,
                                prompt_embeds=prompt_embeds)


def export_synthesizer(out: Path, *, num_frames: int, height: int, width: int, base_dir: Path | None = None,
                       control_dir: Path | None = None, random: RandomPreset | None = None, prompt: str = "",
                       seed: int = 0) -> Path:
    _need_source("synthesizer", random, base_dir)
    if random == "full":
        raise NotImplementedError("export-synthesizer --random full is not provided: a random 1.3B-width DiT "
                                  "is timed by benchmarks/synthesis.py --config wan-1.3b instead")
    return onnx_export.export_synthesizer(Path(out), base_dir=base_dir, control_dir=control_dir, tiny=random == "tiny",
                                          num_frames=num_frames, height=height, width=width, prompt=prompt, seed=seed)


def export_fun_camera(out_dir: Path, *, checkpoint_dir: Path | None = None, random: RandomPreset | None = None,
                      num_frames: int, height: int, width: int, seed: int = 0, base_dir: Path | None = None,
                      prompt: str = "") -> Path:
    """The fun-camera synthesizer (Wan2.1-Fun-V1.1-Control-Camera, ``models/synthesis/funcamera/``) into
    ``out_dir``; runs select it with ``synthesis.model = "fun-camera"``.

    ``checkpoint_dir``: the official model folder (``config.json`` + ``diffusion_pytorch_model*.safetensors``, read
    with strict key/shape checks), with ``base_dir``: a diffusers-format Wan2.1 I2V directory for the VAE, CLIP image
    encoder and UMT5 (the Fun folder's ``.pth`` encoders are not read). ``random="tiny"``: tiny random weights
    (tests); ``"full"`` is not built. ``num_frames`` / ``height`` / ``width`` as for ``export_synthesizer``.
    """
    if (random is None) == (checkpoint_dir is None):
        raise ValueError("export_fun_camera: give either checkpoint_dir (the official Wan2.1-Fun-V1.1-*-Control-Camera "
                         "folder) or random='tiny' (random weights, for tests)")
    if random == "full":
        raise NotImplementedError("export_fun_camera(random='full') is not provided: a random 1.3B-width export "
                                  "only times the DiT; use funcamera.build_fun_camera(FunCameraConfig.wan_1_3b())")
    if random is not None and base_dir is not None:
        raise ValueError("export_fun_camera: base_dir goes with checkpoint_dir, not random")
    return onnx_export.export_fun_camera_synthesizer(Path(out_dir), checkpoint_dir=checkpoint_dir, base_dir=base_dir,
                                                     tiny=random == "tiny", num_frames=num_frames, height=height,
                                                     width=width, prompt=prompt, seed=seed)


def export_all(model_dir: Path, *, num_frames: int, height: int, width: int, random: RandomPreset = "tiny",
               seed: int = 0, prompt: str = "") -> dict[str, Path]:
    """All three roles with random weights into ``model_dir/{synthesizer,geometry,monodepth}``."""
    model_dir = Path(model_dir)
    return {
        "synthesizer": export_synthesizer(role_dir(model_dir, "synthesizer"), num_frames=num_frames,
                                          height=height, width=width, random=random, seed=seed,
                                          prompt=prompt),
        "geometry": export_geometry(role_dir(model_dir, "geometry"), random=random, seed=seed),
        "monodepth": export_monodepth(role_dir(model_dir, "monodepth"), random=random, seed=seed),
    }
