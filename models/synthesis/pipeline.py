"""The synthesizer's sampler: camera-controlled Wan2.1 I2V, DPM-solver for flow matching, classifier-free guidance.

The same sampling code drives two engines through a small *runner* interface (numpy float32 in and out):

* ``TorchRunner(components)``: the torch modules of ``export.SynthesisComponents`` (eager, fp32; any device).
* ``OrtRunner(model_dir)``: the ONNX graphs of an exported model directory, on onnxruntime.

A runner has ``config`` (the model directory manifest's ``config``), ``fixed_num_frames`` (the frame count its
VAE graphs were exported for, or ``None``) and four calls: ``encode_image_clip``, ``vae_encode``, ``vae_decode``
and ``dit`` (see ``Runner``).

Sampling (``sample_video``), following diffusers' ``WanImageToVideoPipeline`` where it applies:

1. the I2V condition video (frame 0 = the input image, the other frames zero) and the point-cloud renders are
   VAE-encoded (one batch of 2) to normalised latents ``[16, F, h, w]`` (``F = (T-1)/4 + 1``, ``h = H/8``);
2. Wan's I2V mask (4 channels: latent frame 0 = 1, others 0) goes in front of the condition latents:
   ``hidden_states = [noisy latents (16) | mask (4) | condition latents (16)]`` = 36 channels;
3. the render condition ``cond`` = render latents (16) + the visibility masks packed like the I2V mask
   (4 channels; ``camcontrol.pack_visibility_mask``: 8x8 average pooling, frame 0 repeated 4 times);
4. CLIP image features of the input image (penultimate layer, as Wan I2V);
   the **extra reference frame** (``image_reference`` / ``image_reference_plucker``, see ``camcontrol``): the
   reference image (the scene's input photo when the clip starts elsewhere) VAE-encoded as a one-frame video,
   with its Plücker rays in the clip's frame; without one, the conditioning image itself with the rays of the
   clip's first camera (the latent frame 0 of step 1, so no extra encoding);
5. initial noise ``[1, 16, F, h, w]`` from a CPU ``torch.Generator`` seeded with ``cfg.seed`` (so the same seed
   gives the same video on every engine and provider);
6. ``cfg.steps`` steps of ``DPMSolverMultistepScheduler(prediction_type="flow_prediction", use_flow_sigmas=True,
   flow_shift=cfg.flow_shift)`` (DPM-solver++ 2M); each step is ONE DiT call on a batch of 2 (conditional and
   unconditional text) combined as ``uncond + guidance_scale * (cond - uncond)``.
   **The unconditional branch keeps the camera control on**: same Plücker rays, render condition, input image
   and CLIP features; only the text embedding differs (the negative prompt). As in Wan I2V, where the image
   condition stays in both branches, guidance then sharpens the text/appearance prior but never amplifies or
   cancels the camera (a camera-free uncond branch would make CFG extrapolate the camera signal 6.5x);
7. the final latents are VAE-decoded, mapped from [-1, 1] to uint8.

A **fun-camera** model directory (manifest ``config.condition_layout = "fun-camera"``, ``funcamera/``) is sampled by
the same loop with its own conditions (``_fun_camera_conditions``): ``hidden_states = [noisy (16) | start-image
latents (16)]`` (latent frame 0 = the image, later frames zero, no mask), CLIP features, the rays; no render
condition and no reference frame (those DiT inputs are None and the graph has none).

Precision: fp32 everywhere. onnxruntime's CPU EP has no bf16 kernels (fp16 is emulated and slower), and the CUDA
EP runs the same fp32 graphs (TF32 matmuls where the GPU allows; bf16 has kernel gaps in the CUDA EP, see
``models/runtime/onnxio.py``). The scheduler arithmetic always runs in fp32 torch on the CPU.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from navcrafter.models.runtime.onnxio import GraphRunner, load_manifest
from navcrafter.models.synthesis.config import WAN_FLOW_SHIFT, SynthesisConfig


class SynthesisShapeError(ValueError):
    """Inputs do not fit the model (frame count, size, channel layout); the message names the fix."""




@dataclass(frozen=True)
class SamplerConfig:
    """The settings of one sampling call, resolved from the run's ``synthesis`` section (the one definition of
    every sampling parameter and its default: DPM-solver 40 steps, CFG 6.5, camera LoRA 0.7) by
    :func:`sampler_settings`; no defaults of its own."""

    steps: int
    guidance_scale: float
    lora_scale: float
    flow_shift: float
    seed: int

    def __post_init__(self) -> None:
        if self.steps < 1:
            raise ValueError(f"steps must be >= 1, got {self.steps}")
        if self.flow_shift <= 0:
            raise ValueError(f"flow_shift must be positive, got {self.flow_shift}")


def sampler_settings(synthesis: SynthesisConfig, seed: int, scheduler: dict | None = None) -> SamplerConfig:
    """One call's settings: ``synthesis`` (steps, CFG, LoRA scale, and ``flow_shift`` when set), else the exported
    model's scheduler shift (its manifest's ``scheduler``), else Wan2.1's."""
    shift = synthesis.flow_shift
    if shift is None:
        shift = float((scheduler or {}).get("flow_shift", WAN_FLOW_SHIFT))
    return SamplerConfig(steps=synthesis.steps, guidance_scale=synthesis.guidance_scale,
                         lora_scale=synthesis.lora_scale, flow_shift=float(shift), seed=int(seed))


class Runner(Protocol):
    config: dict[str, Any]
    fixed_num_frames: int | None

    def encode_image_clip(self, pixel_values: np.ndarray) -> np.ndarray:
        """``[B, 3, S, S]`` CLIP-normalised pixels -> image features ``[B, L, image_dim]``."""

    def vae_encode(self, video: np.ndarray) -> np.ndarray:
        """``[B, 3, T, H, W]`` in [-1, 1] -> normalised latents ``[B, 16, F, H/8, W/8]``."""

    def vae_decode(self, latents: np.ndarray) -> np.ndarray:
        """Normalised latents ``[B, 16, F, h, w]`` -> video ``[B, 3, T, 8h, 8w]`` in [-1, 1]."""

    def dit(self, hidden_states: np.ndarray, timestep: np.ndarray, encoder_hidden_states: np.ndarray,
            encoder_hidden_states_image: np.ndarray, plucker: np.ndarray, cond: np.ndarray,
            lora_scale: np.ndarray, image_reference: np.ndarray, image_reference_plucker: np.ndarray) -> np.ndarray:
        """Flow prediction ``[B, 16, F, h, w]`` (inputs as ``CameraControlledWan.forward``: ``image_reference``
        ``[B, 16, R, h, w]``, ``image_reference_plucker`` ``[B, 6, R, H, W]``)."""


# --------------------------------------------------------------------------------------------------
# Runners
# --------------------------------------------------------------------------------------------------
class TorchRunner:
    """Eager torch engine over ``export.SynthesisComponents`` (the modules the ONNX graphs are exported from)."""

    def __init__(self, components, num_frames: int | None = None, height: int | None = None,
                 width: int | None = None, device: str = "cpu") -> None:
        import torch

        # deferred: torch (onnx_export) loads only for the torch runner
        from navcrafter.models.synthesis.onnx_export import ClipImageFeatures, VaeDecoder, VaeEncoder

        self.torch = torch
        self.device = torch.device(device)
        self.components = components
        self.config = components.config(num_frames or 0, height or 0, width or 0)
        self.fixed_num_frames = None
        self._dit = components.dit.to(self.device).eval()
        self._enc = VaeEncoder(components.vae).to(self.device).eval()
        self._dec = VaeDecoder(components.vae).to(self.device).eval()
        self._clip = ClipImageFeatures(components.image_encoder).to(self.device).eval()

    def _t(self, x: np.ndarray):
        return self.torch.as_tensor(np.asarray(x, dtype=np.float32), device=self.device)

    def _run(self, fn, *args) -> np.ndarray:
        with self.torch.no_grad():
            return fn(*(None if a is None else self._t(a) for a in args)).float().cpu().numpy()

    def encode_image_clip(self, pixel_values: np.ndarray) -> np.ndarray:
        return self._run(self._clip, pixel_values)

    def vae_encode(self, video: np.ndarray) -> np.ndarray:
        return self._run(self._enc, video)

    def vae_decode(self, latents: np.ndarray) -> np.ndarray:
        return self._run(self._dec, latents)

    def dit(self, hidden_states, timestep, encoder_hidden_states, encoder_hidden_states_image, plucker, cond,
            lora_scale, image_reference, image_reference_plucker) -> np.ndarray:
        return self._run(self._dit, hidden_states, timestep, encoder_hidden_states, encoder_hidden_states_image,
                         plucker, cond, lora_scale, image_reference, image_reference_plucker)


_ORT_TYPES = {"tensor(float)": np.float32, "tensor(float16)": np.float16, "tensor(double)": np.float64,
              "tensor(int64)": np.int64, "tensor(int32)": np.int32}


class OrtRunner:
    """onnxruntime engine over an exported synthesizer directory (``export.export_synthesizer``).

    ``providers`` default to CUDA when onnxruntime has it, else CPU (``onnxio.default_providers``). Every graph
    is fp32 (see the module docstring). Inputs are cast to each graph input's declared element type.
    """

    def __init__(self, model_dir: str | Path, providers: list[str] | None = None, verify: bool = True,
                 offload: bool = False) -> None:
        # deferred: onnx_export imports torch; the onnxruntime runner needs only its KIND
        from navcrafter.models.synthesis.onnx_export import KIND

        self.model_dir = Path(model_dir)
        # offload: one graph's session at a time (VAE encoder, image encoder, DiT, VAE decoder in turn): the others'
        # weights are off the device, reloaded (from the page cache) when next needed; outputs are unchanged
        self.offload = offload
        self.manifest = load_manifest(self.model_dir, KIND, verify=verify)
        self.config = self.manifest["config"]
        self.fixed_num_frames = int(self.config["vae_num_frames"])
        self.graphs = GraphRunner(self.model_dir, self.manifest, providers)

    @property
    def providers(self) -> list[str]:
        return self.graphs.providers

    def text_embeddings(self) -> tuple[np.ndarray, np.ndarray]:
        """(prompt, negative prompt) embeddings ``[512, text_dim]`` stored at export time."""
        emb = np.load(self.model_dir / self.config["text"]["file"])
        return emb[0], emb[1]

    def _session(self, graph: str):
        if self.offload:
            self.graphs.release(keep=graph)
        return self.graphs.session(graph)

    def _call(self, graph: str, values: dict[str, np.ndarray]) -> np.ndarray:
        sess = self._session(graph)
        feeds = {}
        for inp in sess.get_inputs():
            if inp.name not in values:
                raise SynthesisShapeError(f"{self.model_dir}: graph {graph} wants input {inp.name!r} the sampler "
                                          f"does not provide; re-export the model with this navcrafter version")
            feeds[inp.name] = np.ascontiguousarray(values[inp.name], dtype=_ORT_TYPES.get(inp.type, np.float32))
        out = sess.run(None, feeds)[0]
        return np.asarray(out, dtype=np.float32)

    def encode_image_clip(self, pixel_values: np.ndarray) -> np.ndarray:
        return self._call("image_encoder", {"pixel_values": pixel_values})

    def vae_encode(self, video: np.ndarray) -> np.ndarray:
        return self._call("vae_encoder", {"video": video})

    def vae_decode(self, latents: np.ndarray) -> np.ndarray:
        return self._call("vae_decoder", {"latents": latents})

    def dit(self, hidden_states, timestep, encoder_hidden_states, encoder_hidden_states_image, plucker, cond,
            lora_scale, image_reference, image_reference_plucker) -> np.ndarray:
        names = {i.name for i in self._session("dit").get_inputs()}
        if "image_reference" not in names and condition_layout(self.config) == "navcrafter":
            raise SynthesisShapeError(f"{self.model_dir}: its DiT graph has no image_reference input (exported before "
                                      f"extra reference frames), so the reference would be dropped; re-export the "
                                      f"model with this navcrafter version")
        return self._call("dit", {"hidden_states": hidden_states, "timestep": timestep,
                                  "encoder_hidden_states": encoder_hidden_states,
                                  "encoder_hidden_states_image": encoder_hidden_states_image, "plucker": plucker,
                                  "cond": cond, "lora_scale": lora_scale, "image_reference": image_reference,
                                  "image_reference_plucker": image_reference_plucker})


# --------------------------------------------------------------------------------------------------
# Preprocessing
# --------------------------------------------------------------------------------------------------
def clip_preprocess(image: np.ndarray, params: dict[str, Any]) -> np.ndarray:
    """``CLIPImageProcessor`` for one uint8 ``[H, W, 3]`` image -> ``[1, 3, S, S]`` float32.

    Shortest edge resized to ``shortest_edge`` (PIL bicubic), centre crop ``image_size``, [0, 1], mean/std.
    """
    from PIL import Image

    img = Image.fromarray(np.asarray(image, dtype=np.uint8))
    short, crop = int(params["shortest_edge"]), int(params["image_size"])
    w, h = img.size
    scale = short / min(w, h)
    nw, nh = (short, max(short, int(h * scale))) if w <= h else (max(short, int(w * scale)), short)
    img = img.resize((nw, nh), Image.BICUBIC)
    left, top = (nw - crop) // 2, (nh - crop) // 2
    img = img.crop((left, top, left + crop, top + crop))
    x = np.asarray(img, dtype=np.float32) / 255.0
    x = (x - np.asarray(params["image_mean"], np.float32)) / np.asarray(params["image_std"], np.float32)
    return x.transpose(2, 0, 1)[None].astype(np.float32)


def _to_video(frames: np.ndarray) -> np.ndarray:
    """uint8 ``[T, H, W, 3]`` -> float32 ``[3, T, H, W]`` in [-1, 1]."""
    return (np.asarray(frames, dtype=np.float32).transpose(3, 0, 1, 2) / 127.5 - 1.0).astype(np.float32)


def i2v_mask(num_latent_frames: int, h: int, w: int, temporal: int = 4) -> np.ndarray:
    """Wan2.1 I2V mask ``[temporal, F, h, w]``: 1 on latent frame 0 (the given image), 0 elsewhere."""
    m = np.zeros((temporal, num_latent_frames, h, w), dtype=np.float32)
    m[:, 0] = 1.0
    return m


def condition_layout(config: dict) -> str:
    """The DiT's input layout a model directory's manifest ``config`` records: ``"navcrafter"`` (absent: NavCrafter's
    camera control, the I2V mask layout with render condition and reference frame) or ``"fun-camera"``
    (``funcamera/``: ``[noisy | start-image latents]``, camera rays only)."""
    layout = config.get("condition_layout", "navcrafter")
    if layout not in ("navcrafter", "fun-camera"):
        raise SynthesisShapeError(f"unknown condition_layout {layout!r} in the model's manifest: re-export it with "
                                  f"this navcrafter version")
    return layout


def check_inputs(runner: Runner, image: np.ndarray, plucker: np.ndarray, renders: np.ndarray,
                 masks: np.ndarray, reference_image: np.ndarray | None = None,
                 reference_plucker: np.ndarray | None = None) -> tuple[int, int, int]:
    """Shapes of one sampling call against each other and the model; returns ``(T, H, W)``."""
    cfg = runner.config
    st, ss = int(cfg["vae_scale_factor_temporal"]), int(cfg["vae_scale_factor_spatial"])
    ph, pw = cfg["patch_size"][1:]
    image, plucker, renders, masks = (np.asarray(a) for a in (image, plucker, renders, masks))
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise SynthesisShapeError(f"image must be uint8 [H, W, 3], got {image.dtype} {image.shape}")
    H, W = image.shape[:2]
    if plucker.ndim != 4 or plucker.shape[1:] != (H, W, 6):
        raise SynthesisShapeError(f"plucker must be [T, {H}, {W}, 6] (image size), got {plucker.shape}")
    T = plucker.shape[0]
    if renders.shape != (T, H, W, 3) or renders.dtype != np.uint8:
        raise SynthesisShapeError(f"renders must be uint8 [{T}, {H}, {W}, 3], got {renders.dtype} {renders.shape}")
    if masks.shape != (T, H, W):
        raise SynthesisShapeError(f"masks must be [{T}, {H}, {W}], got {masks.shape}")
    if reference_image is not None:
        ref = np.asarray(reference_image)
        if ref.shape != (H, W, 3) or ref.dtype != np.uint8:
            raise SynthesisShapeError(f"reference_image must be uint8 [{H}, {W}, 3] (the frame size), got "
                                      f"{ref.dtype} {ref.shape}: resize it like the conditioning image")
        if reference_plucker is None:
            raise SynthesisShapeError("reference_image needs reference_plucker: its rays [1, H, W, 6] in the clip's "
                                      "Plücker frame (cameras.clip_relative_rays with the trajectory)")
    if reference_plucker is not None:
        if reference_image is None:
            raise SynthesisShapeError("reference_plucker given without reference_image")
        if np.asarray(reference_plucker).shape not in ((H, W, 6), (1, H, W, 6)):
            raise SynthesisShapeError(f"reference_plucker must be [1, {H}, {W}, 6], got "
                                      f"{np.asarray(reference_plucker).shape}")
    if runner.fixed_num_frames is not None and T != runner.fixed_num_frames:
        raise SynthesisShapeError(
            f"got {T} frames but this synthesizer's VAE graphs were exported for num_frames="
            f"{runner.fixed_num_frames} (the Wan VAE exports for one frame count): set synthesis.num_frames="
            f"{runner.fixed_num_frames} or re-export with export_synthesizer(..., num_frames={T})")
    if T < st + 1 or (T - 1) % st:
        raise SynthesisShapeError(f"the number of frames must be {st}k+1 (Wan VAE), got {T}")
    if H % (ss * ph) or W % (ss * pw):
        raise SynthesisShapeError(f"height and width must be multiples of {ss * ph}x{ss * pw}, got {H}x{W}")
    if not cfg.get("dynamic_shapes", True) and (H, W) != (cfg["height"], cfg["width"]):
        raise SynthesisShapeError(
            f"got {W}x{H} frames but this synthesizer was exported for {cfg['width']}x{cfg['height']} with "
            f"static shapes: set synthesis.height={cfg['height']}, synthesis.width={cfg['width']} or "
            f"re-export with export_synthesizer(..., height={H}, width={W})")
    return T, H, W


def _text(emb: np.ndarray, cfg: dict) -> np.ndarray:
    e = np.asarray(emb, dtype=np.float32)
    if e.ndim == 3 and e.shape[0] == 1:
        e = e[0]
    tokens, dim = int(cfg.get("text_tokens", 512)), int(cfg["text_dim"])
    if e.shape != (tokens, dim):
        raise SynthesisShapeError(f"text embeddings must be [{tokens}, {dim}] (UMT5, padded to {tokens} tokens), "
                                  f"got {e.shape}")
    return e


# --------------------------------------------------------------------------------------------------
# Sampling
# --------------------------------------------------------------------------------------------------
def make_scheduler(cfg: SamplerConfig, scheduler_config: dict | None = None):
    from diffusers import DPMSolverMultistepScheduler

    sc = scheduler_config or {}
    return DPMSolverMultistepScheduler(
        num_train_timesteps=int(sc.get("num_train_timesteps", 1000)), solver_order=int(sc.get("solver_order", 2)),
        algorithm_type=sc.get("algorithm_type", "dpmsolver++"), prediction_type="flow_prediction",
        use_flow_sigmas=True, flow_shift=float(cfg.flow_shift))


def _first_frame_video(image: np.ndarray, T: int) -> np.ndarray:
    """``[3, T, H, W]``: ``image`` as frame 0, the other frames zero (Wan I2V's condition video)."""
    video = np.zeros((3, T, *np.asarray(image).shape[:2]), dtype=np.float32)
    video[:, 0] = _to_video(np.asarray(image)[None])[:, 0]
    return video


def _vae_encode(runner: Runner, videos: list[np.ndarray]) -> np.ndarray:
    """Encode ``[3, T, H, W]`` videos: one call when the VAE graph's batch is dynamic, else in pairs (a static
    export's encoder takes batch 2; an odd last one is repeated)."""
    if runner.config.get("dynamic_shapes", True):
        return runner.vae_encode(np.stack(videos))
    out = []
    for i in range(0, len(videos), 2):
        pair = videos[i:i + 2]
        out.append(runner.vae_encode(np.stack(pair * (3 - len(pair))))[:len(pair)])
    return np.concatenate(out)


def prepare_conditions(runner: Runner, image: np.ndarray, plucker: np.ndarray, renders: np.ndarray,
                       masks: np.ndarray, reference_image: np.ndarray | None = None,
                       reference_plucker: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Everything the DiT sees besides the noisy latents and the text, for batch 1.

    ``reference_image`` uint8 ``[H, W, 3]`` with ``reference_plucker [1, H, W, 6]`` (its rays in the clip's Plücker
    frame): the extra reference frame, VAE-encoded as a one-frame video (the Wan VAE is causal, so latent frame 0
    of a video whose frame 0 is the image is that one-frame encoding: the fixed-frame-count graph serves). Without
    one, the conditioning image and the rays of the clip's first camera (``plucker[0]``).
    """
    import torch

    # deferred: diffusers loads with camcontrol only when conditions are prepared, not on import
    from navcrafter.models.synthesis.camcontrol import pack_visibility_mask

    T, H, W = check_inputs(runner, image, plucker, renders, masks, reference_image, reference_plucker)
    cfg = runner.config
    st = int(cfg["vae_scale_factor_temporal"])
    if condition_layout(cfg) == "fun-camera":
        return _fun_camera_conditions(runner, image, plucker, reference_image, T)
    condition = _first_frame_video(image, T)
    videos = [condition, _to_video(renders)]
    if reference_image is not None:
        videos.append(_first_frame_video(reference_image, T))
    latents = _vae_encode(runner, videos)  # [2 or 3, 16, F, h, w]
    cond_lat, render_lat = latents[0:1], latents[1:2]
    if reference_image is not None:
        ref_lat = latents[2:3, :, :1]
        ref_rays = np.asarray(reference_plucker, dtype=np.float32).reshape(1, H, W, 6)
    else:
        ref_lat = cond_lat[:, :, :1]
        ref_rays = np.asarray(plucker, dtype=np.float32)[:1]
    F, h, w = cond_lat.shape[2:]
    hidden_cond = np.concatenate([i2v_mask(F, h, w, st)[None], cond_lat], axis=1)  # [1, 20, F, h, w]
    expected = int(cfg["control"]["cond_channels"])
    cond = None  # a control trained without render conditioning (cond_channels = 0) has no such input
    if expected:
        vis = pack_visibility_mask(torch.as_tensor(np.asarray(masks, dtype=np.float32))[None],
                                   (st, int(cfg["vae_scale_factor_spatial"]), int(cfg["vae_scale_factor_spatial"])))
        cond = np.concatenate([render_lat, vis.numpy().astype(np.float32)], axis=1)  # [1, 20, F, h, w]
        if cond.shape[1] != expected:
            raise SynthesisShapeError(f"render condition has {cond.shape[1]} channels, the DiT expects {expected}")
    clip = runner.encode_image_clip(clip_preprocess(image, cfg["image_encoder"]))
    plk = np.ascontiguousarray(np.asarray(plucker, dtype=np.float32).transpose(3, 0, 1, 2)[None])
    ref_plk = np.ascontiguousarray(ref_rays.transpose(3, 0, 1, 2)[None])  # [1, 6, 1, H, W]
    return {"hidden_cond": hidden_cond, "cond": cond, "image_embeds": clip, "plucker": plk,
            "image_reference": np.ascontiguousarray(ref_lat, dtype=np.float32), "image_reference_plucker": ref_plk,
            "latent_shape": np.array([F, h, w])}


def _fun_camera_conditions(runner: Runner, image: np.ndarray, plucker: np.ndarray,
                           reference_image: np.ndarray | None, T: int) -> dict[str, np.ndarray]:
    """Conditions of a fun-camera DiT (VideoX-Fun ``pipeline_wan_fun_control.py`` with ``control_camera_video`` and
    ``start_image``): the start image VAE-encoded as a one-frame video into latent frame 0 of otherwise **zero**
    latents (no mask; the causal VAE's latent frame 0 of ``[image, 0, ...]`` is that one-frame encoding), CLIP
    features of the same image, the rays. No render condition, no reference frames (renders and masks unused)."""
    if reference_image is not None:
        raise SynthesisShapeError("the fun-camera model has no extra reference frame: pass no reference_image")
    cfg = runner.config
    lat = _vae_encode(runner, [_first_frame_video(image, T)])  # [1, 16, F, h, w]
    start = np.zeros_like(lat)
    start[:, :, :1] = lat[:, :, :1]
    F, h, w = lat.shape[2:]
    clip = runner.encode_image_clip(clip_preprocess(image, cfg["image_encoder"]))
    plk = np.ascontiguousarray(np.asarray(plucker, dtype=np.float32).transpose(3, 0, 1, 2)[None])
    return {"hidden_cond": start.astype(np.float32), "cond": None, "image_embeds": clip, "plucker": plk,
            "image_reference": None, "image_reference_plucker": None, "latent_shape": np.array([F, h, w])}


def initial_noise(seed: int, channels: int, F: int, h: int, w: int) -> np.ndarray:
    """Seeded Gaussian noise ``[1, C, F, h, w]`` from a CPU torch Generator (same on every engine/provider)."""
    import torch

    g = torch.Generator(device="cpu").manual_seed(int(seed))
    return torch.randn((1, channels, F, h, w), generator=g, dtype=torch.float32).numpy()


def sample_latents(runner: Runner, image: np.ndarray, plucker: np.ndarray, renders: np.ndarray, masks: np.ndarray,
                   text_emb: np.ndarray, neg_text_emb: np.ndarray, cfg: SamplerConfig,
                   conditions: dict[str, np.ndarray] | None = None, callback=None,
                   reference_image: np.ndarray | None = None,
                   reference_plucker: np.ndarray | None = None) -> np.ndarray:
    """The denoised normalised latents ``[1, 16, F, h, w]`` (steps 1-6 of the module docstring).

    ``conditions`` may be passed in (``prepare_conditions``) to reuse the encoded inputs across seeds.
    ``callback(step, timestep, latents)`` is called after every step. ``reference_image`` /
    ``reference_plucker``: the extra reference frame (``prepare_conditions``).
    """
    import torch

    mcfg = runner.config
    pos, neg = _text(text_emb, mcfg), _text(neg_text_emb, mcfg)
    c = conditions if conditions is not None else prepare_conditions(runner, image, plucker, renders, masks,
                                                                     reference_image, reference_plucker)
    F, h, w = (int(v) for v in c["latent_shape"])
    channels = int(mcfg["latent_channels"])
    latents = torch.from_numpy(initial_noise(cfg.seed, channels, F, h, w))

    def pair(a):  # CFG pair: the same conditions in both rows (None: an input the model does not have)
        return None if a is None else np.concatenate([a, a], axis=0)

    text = np.stack([pos, neg])
    image_embeds, plucker2 = pair(c["image_embeds"]), pair(c["plucker"])
    cond2 = pair(c["cond"])
    hidden_cond2 = pair(c["hidden_cond"])
    ref2, ref_plucker2 = pair(c["image_reference"]), pair(c["image_reference_plucker"])
    lora = np.asarray(cfg.lora_scale, dtype=np.float32)

    scheduler = make_scheduler(cfg, mcfg.get("scheduler"))
    scheduler.set_timesteps(cfg.steps, device="cpu")
    for i, t in enumerate(scheduler.timesteps):
        x = latents.numpy().astype(np.float32)
        hidden = np.concatenate([pair(x), hidden_cond2], axis=1)
        timestep = np.full((2,), float(t), dtype=np.float32)
        pred = runner.dit(hidden, timestep, text, image_embeds, plucker2, cond2, lora, ref2, ref_plucker2)
        guided = pred[1:2] + cfg.guidance_scale * (pred[0:1] - pred[1:2])
        latents = scheduler.step(torch.from_numpy(guided), t, latents, return_dict=False)[0].float()
        if callback is not None:
            callback(i, float(t), latents.numpy())
    return latents.numpy().astype(np.float32)


def video_to_frames(video: np.ndarray) -> np.ndarray:
    """A decoded video float ``[3, T, H, W]`` in [-1, 1] -> uint8 frames ``[T, H, W, 3]`` (``_to_video``'s inverse)."""
    video = np.clip((np.asarray(video) + 1.0) * 127.5, 0.0, 255.0)
    return np.rint(video).astype(np.uint8).transpose(1, 2, 3, 0).copy()


def decode_video(runner: Runner, latents: np.ndarray) -> np.ndarray:
    """Normalised latents ``[1, 16, F, h, w]`` -> uint8 frames ``[T, H, W, 3]``."""
    return video_to_frames(runner.vae_decode(np.asarray(latents, dtype=np.float32))[0])


def sample_video(runner: Runner, image: np.ndarray, plucker: np.ndarray, renders: np.ndarray, masks: np.ndarray,
                 text_emb: np.ndarray, neg_text_emb: np.ndarray, cfg: SamplerConfig,
                 reference_image: np.ndarray | None = None, reference_plucker: np.ndarray | None = None
                 ) -> np.ndarray:
    """Frames ``[T, H, W, 3]`` uint8 for ``image`` uint8 ``[H, W, 3]``, Plücker rays ``[T, H, W, 6]``, point-cloud
    renders uint8 ``[T, H, W, 3]`` with visibility ``masks`` bool ``[T, H, W]`` and text embeddings ``[512, D]``;
    optionally an extra reference frame (``reference_image`` ``[H, W, 3]``, its rays ``[1, H, W, 6]``)."""
    latents = sample_latents(runner, image, plucker, renders, masks, text_emb, neg_text_emb, cfg,
                             reference_image=reference_image, reference_plucker=reference_plucker)
    return decode_video(runner, latents)
