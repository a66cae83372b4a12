"""``CameraControlledWan``: diffusers' ``WanTransformer3DModel`` wrapped with the camera control, and its
constructors."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
import torch.nn as nn
from diffusers.models.transformers.transformer_wan import WanTransformer3DModel

from navcrafter.models.synthesis.camcontrol.attention import CameraControlAttnProcessor, _ControlState
from navcrafter.models.synthesis.camcontrol.conditioning import _runs, _take_frames, select_reference_frames
from navcrafter.models.synthesis.camcontrol.config import (
    CONTROL_CONFIG,
    TINY_I2V_CONFIG,
    TRAINING_LORA_SCALE,
    CameraControlConfig,
    CameraControlWeightsError,
    tiny_camera_config,
)
from navcrafter.models.synthesis.camcontrol.modules import CameraControl
from navcrafter.models.synthesis.camcontrol.weights import (
    _dict_diff,
    load_camera_control,
    load_wan_transformer,
    read_camera_control_config,
)


class CameraControlledWan(nn.Module):
    """``base`` (diffusers ``WanTransformer3DModel``) + ``control`` (``CameraControl``).

    ``forward(hidden_states [B, C_in, F, h, w], timestep [B], encoder_hidden_states [B, 512, text_dim],
    encoder_hidden_states_image [B, L_img, image_dim] | None, plucker [B, 6, 4(F-1)+1, 8h, 8w] | None,
    cond [B, cond_channels, F, h, w] | None, lora_scale: scalar tensor | float | None,
    image_reference [B, 16, R, h, w] | None, image_reference_plucker [B, 6, R, 8h, 8w] | None)
    -> noise/flow prediction [B, out_channels, F, h, w]``.
    """

    def __init__(self, base: WanTransformer3DModel, config: CameraControlConfig | None = None) -> None:
        super().__init__()
        self.base = base
        self.config = config or CameraControlConfig()
        self.control = CameraControl(self.config, base.config)
        self.control.to(device=base.device, dtype=base.dtype)
        self.init_reference_embedding_from_base()
        for i, block in enumerate(base.blocks):
            block.attn1.set_processor(CameraControlAttnProcessor(i))
        self._ref_generator = torch.Generator().manual_seed(self.config.reference_seed)
        self.gradient_checkpointing = False

    # ---- construction / weights -------------------------------------------------------------------
    @torch.no_grad()
    def init_reference_embedding_from_base(self) -> None:
        """Reference-token embedding = the base patch embedding of a *known clean frame* (I2V layout:
        noisy channels = clean latent, mask = 1, condition channels = clean latent); for a T2V base the
        first ``latent_channels`` input channels. Only changes ``control.ref_embedding``."""
        w, b = self.base.patch_embedding.weight, self.base.patch_embedding.bias
        c = self.config.latent_channels
        in_ch = w.shape[1]
        if in_ch == 2 * c + 4:  # [noisy | mask(4) | condition]
            weight = w[:, :c] + w[:, c + 4:]
            bias = b + w[:, c:c + 4].sum(dim=(1, 2, 3, 4))
        elif in_ch >= c:
            weight, bias = w[:, :c], b
        else:
            return
        self.control.ref_embedding.weight.copy_(weight)
        self.control.ref_embedding.bias.copy_(bias)

    @classmethod
    def from_pretrained(cls, base_dir: str | os.PathLike, control_dir: str | os.PathLike | None = None,
                        config: CameraControlConfig | None = None, torch_dtype: torch.dtype | None = None,
                        ) -> CameraControlledWan:
        """Base from a diffusers directory (``<base_dir>/transformer`` or ``base_dir`` itself); control
        weights from ``control_dir`` (``save_camera_control``'s files), or fresh zero-initialised ones."""
        base = load_wan_transformer(base_dir, torch_dtype=torch_dtype)
        if control_dir is not None:
            saved = read_camera_control_config(control_dir)
            if config is not None and config.to_dict() != saved.to_dict():
                raise CameraControlWeightsError(
                    f"{Path(control_dir) / CONTROL_CONFIG}: config differs from the one passed "
                    f"({_dict_diff(saved.to_dict(), config.to_dict())}); pass config=None to use the saved one")
            config = saved
        model = cls(base, config)
        if control_dir is not None:
            load_camera_control(model, control_dir)
        return model

    def freeze_base(self) -> None:
        """Train only the camera control: ``requires_grad=False`` on every base parameter."""
        self.base.requires_grad_(False)

    def seed_reference_frames(self, seed: int) -> None:
        """Reseed the training-time reference-frame generator."""
        self._ref_generator = torch.Generator().manual_seed(int(seed))

    def _processors(self) -> list[CameraControlAttnProcessor]:
        procs = [block.attn1.processor for block in self.base.blocks]
        for p in procs:
            if not isinstance(p, CameraControlAttnProcessor):
                raise RuntimeError(f"attn1 processor was replaced by {type(p).__name__}; camera control needs "
                                   f"CameraControlAttnProcessor")
        return procs

    # ---- forward ----------------------------------------------------------------------------------
    def reference_indices(self, num_latent_frames: int,
                          reference_frames: torch.Tensor | Sequence[int] | None = None) -> list[int] | None:
        """Latent frames used as reference frames for this call (see the module docstring), sorted."""
        if reference_frames is not None:
            frames = torch.as_tensor(reference_frames, dtype=torch.long).flatten().tolist()
        elif self.training:
            frames = select_reference_frames(num_latent_frames, self.config.num_reference_frames,
                                             self._ref_generator).tolist()
        else:
            frames = list(self.config.inference_reference_frames)
        frames = sorted(set(int(f) for f in frames))
        bad = [f for f in frames if not 0 <= f < num_latent_frames]
        if bad:
            raise ValueError(f"reference frames {bad} out of range for {num_latent_frames} latent frames")
        return frames or None

    def _reference_rope(self, frames: list[int], pph: int, ppw: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The base rope (``WanRotaryPosEmbed``) evaluated on the token grid of the given latent frames only:
        the same values the base gives those frames' tokens, built from slices (small exported graph)."""
        rope = self.base.rope
        runs = _runs(frames)
        out = []
        for freqs in (rope.freqs_cos, rope.freqs_sin):
            f_t, f_h, f_w = freqs.split([rope.t_dim, rope.h_dim, rope.w_dim], dim=1)
            f_t = torch.cat([f_t[s:s + n] for s, n in runs]) if len(runs) > 1 else f_t[runs[0][0]:sum(runs[0])]
            r = len(frames)
            grid = [f_t.view(r, 1, 1, -1).expand(r, pph, ppw, -1),
                    f_h[:pph].view(1, pph, 1, -1).expand(r, pph, ppw, -1),
                    f_w[:ppw].view(1, 1, ppw, -1).expand(r, pph, ppw, -1)]
            out.append(torch.cat(grid, dim=-1).reshape(1, r * pph * ppw, 1, -1))
        return out[0], out[1]

    def forward(self, hidden_states: torch.Tensor, timestep: torch.Tensor, encoder_hidden_states: torch.Tensor,
                encoder_hidden_states_image: torch.Tensor | None = None, plucker: torch.Tensor | None = None,
                cond: torch.Tensor | None = None, lora_scale: torch.Tensor | float | None = None,
                image_reference: torch.Tensor | None = None, image_reference_plucker: torch.Tensor | None = None, *,
                reference_frames: torch.Tensor | Sequence[int] | None = None,
                reference_latents: torch.Tensor | None = None) -> torch.Tensor:
        """Noise/flow prediction ``[B, out_channels, F, h, w]``.

        ``reference_frames``: latent-frame indices overriding the default selection (random in training,
        ``config.inference_reference_frames`` in eval). ``reference_latents [B, 16, F, h, w]``: clean latents
        the reference frames are taken from (training: the clean video latents); default: the I2V
        conditioning latents in ``hidden_states`` (channels 20:36).
        ``image_reference [B, 16, R, h, w]`` (R >= 1): clean latents of extra reference frames outside the clip
        (e.g. the scene's input photo, VAE-encoded as a one-frame video), and ``image_reference_plucker
        [B, 6, R, 8h, 8w]`` their rays in the clip's Plücker frame (same convention, origin and scale as
        ``plucker``: ``cameras.clip_relative_rays``), required when ``plucker`` is given (without ``plucker`` the
        call is camera-free and they are unused). They join the reference frames at the rope position of latent
        frame 0 (module docstring).
        """
        base, control, cfg = self.base, self.control, self.config
        batch_size, _, num_frames, height, width = hidden_states.shape
        p_t, p_h, p_w = base.config.patch_size
        st_t, st_h, st_w = cfg.vae_stride
        ppf, pph, ppw = num_frames // p_t, height // p_h, width // p_w
        if plucker is not None:
            expected = (batch_size, 6, (num_frames - 1) * st_t + 1, height * st_h, width * st_w)
            if tuple(plucker.shape) != expected:
                raise ValueError(f"plucker must be [B, 6, 4(F-1)+1, 8h, 8w] = {expected} for hidden_states "
                                 f"{tuple(hidden_states.shape)}, got {tuple(plucker.shape)}")
        if cond is not None and cfg.cond_channels == 0:
            raise ValueError("cond given but the camera-control config has cond_channels = 0")
        if cond is not None and tuple(cond.shape) != (batch_size, cfg.cond_channels, num_frames, height, width):
            raise ValueError(f"cond must be [B, {cfg.cond_channels}, F, h, w] matching hidden_states "
                             f"{tuple(hidden_states.shape)}, got {tuple(cond.shape)}")
        if image_reference is not None:
            R = image_reference.shape[2] if image_reference.ndim == 5 else 0
            want = (batch_size, cfg.latent_channels, R, height, width)
            if tuple(image_reference.shape) != want or R < 1:
                raise ValueError(f"image_reference must be [B, {cfg.latent_channels}, R, h, w] (R >= 1) matching "
                                 f"hidden_states {tuple(hidden_states.shape)}, got {tuple(image_reference.shape)}")
            if image_reference_plucker is None and plucker is not None:
                raise ValueError("image_reference needs image_reference_plucker (the rays of its frames in the "
                                 "clip's Plücker frame, cameras.clip_relative_rays) when plucker is given")
            if image_reference_plucker is not None:
                want = (batch_size, 6, R, height * st_h, width * st_w)
                if tuple(image_reference_plucker.shape) != want:
                    raise ValueError(f"image_reference_plucker must be [B, 6, R, 8h, 8w] = {want} for image_reference "
                                     f"{tuple(image_reference.shape)}, got {tuple(image_reference_plucker.shape)}")
        elif image_reference_plucker is not None:
            raise ValueError("image_reference_plucker given without image_reference (the frames' clean latents)")
        if lora_scale is None:  # the LoRA is trained at full strength and scaled down at inference (paper: 0.7)
            lora_scale = TRAINING_LORA_SCALE if self.training else cfg.lora_scale
        if not torch.is_tensor(lora_scale):
            lora_scale = torch.tensor(float(lora_scale))
        lora_scale = lora_scale.to(device=hidden_states.device, dtype=hidden_states.dtype).reshape(())

        # ---- base prologue (as WanTransformer3DModel.forward) + render condition -------------------
        rotary_emb = base.rope(hidden_states)
        x = base.patch_embedding(hidden_states)
        if cond is not None:
            x = x + control.cond_embedding(cond.to(x.dtype))
        x = x.flatten(2).transpose(1, 2).contiguous()

        if timestep.ndim == 2:
            ts_seq_len = timestep.shape[1]
            timestep = timestep.flatten()
        else:
            ts_seq_len = None
        temb, timestep_proj, encoder_hidden_states, encoder_hidden_states_image = base.condition_embedder(
            timestep, encoder_hidden_states, encoder_hidden_states_image, timestep_seq_len=ts_seq_len)
        if ts_seq_len is not None:
            timestep_proj = timestep_proj.unflatten(2, (6, -1))
        else:
            timestep_proj = timestep_proj.unflatten(1, (6, -1))
        if encoder_hidden_states_image is not None:
            encoder_hidden_states = torch.concat([encoder_hidden_states_image, encoder_hidden_states], dim=1)

        # ---- control tokens -------------------------------------------------------------------------
        x_c = x_l = None
        if plucker is not None:
            plucker = plucker.to(x.dtype)
            x_c = control.adapter(plucker)
            x_l = control.lora_encoder(plucker)

        ref_tokens = ref_x_c = ref_rope = None
        frames = self.reference_indices(ppf, reference_frames)
        if self.training and frames and reference_latents is None:
            raise ValueError("training mode needs reference_latents (the clean video latents [B, 16, F, h, w]) for "
                             f"its reference frames {frames}: without them they would be taken from the I2V "
                             "conditioning latents, which hold black frames after frame 0")
        src = reference_latents
        if src is None and hidden_states.shape[1] == 2 * cfg.latent_channels + 4:
            src = hidden_states[:, cfg.latent_channels + 4:]
        tokens, cams, ropes = [], [], []  # reference tokens, their camera tokens, their rope
        if frames and src is not None:
            ref = control.ref_embedding(_take_frames(src.to(x.dtype), 2, frames, 1))
            tokens.append(ref.flatten(2).transpose(1, 2))
            ropes.append(self._reference_rope(frames, pph, ppw))
            if x_c is not None:
                cams.append(_take_frames(x_c, 1, frames, pph * ppw))
        if image_reference is not None:  # extra reference frames: rope of latent frame 0 (module docstring)
            ref = control.ref_embedding(image_reference.to(x.dtype))  # [B, D, R, pph, ppw]
            n_ref = ref.shape[2]
            tokens.append(ref.flatten(2).transpose(1, 2))
            cos, sin = self._reference_rope([0], pph, ppw)
            ropes.append((cos.repeat(1, n_ref, 1, 1), sin.repeat(1, n_ref, 1, 1)))
            if image_reference_plucker is not None and x_c is not None:  # each frame's rays as a one-frame clip
                rays = image_reference_plucker.to(x.dtype).transpose(1, 2).flatten(0, 1).unsqueeze(2)
                cam = control.adapter(rays)  # [B * R, pph * ppw, D]
                cams.append(cam.reshape(batch_size, -1, cam.shape[-1]))
        if tokens:
            ref_tokens = tokens[0] if len(tokens) == 1 else torch.cat(tokens, dim=1)
            ref_x_c = None if not cams else cams[0] if len(cams) == 1 else torch.cat(cams, dim=1)
            ref_rope = ropes[0] if len(ropes) == 1 else (torch.cat([r[0] for r in ropes], dim=1),
                                                         torch.cat([r[1] for r in ropes], dim=1))

        state = _ControlState(control=control, x_c=x_c, x_l=x_l, lora_scale=lora_scale, ref_tokens=ref_tokens,
                              ref_x_c=ref_x_c, ref_rope=ref_rope, eps=float(base.config.eps))
        procs = self._processors()

        def run_block(i: int, h: torch.Tensor) -> torch.Tensor:
            if x_c is not None:
                h = h + control.blocks[i].pre_proj(x_c)
            procs[i].state = state
            try:
                return base.blocks[i](h, encoder_hidden_states, timestep_proj, rotary_emb)
            finally:
                procs[i].state = None

        for i in range(len(base.blocks)):
            if torch.is_grad_enabled() and self.gradient_checkpointing and self.training:
                x = torch.utils.checkpoint.checkpoint(run_block, i, x, use_reentrant=False)
            else:
                x = run_block(i, x)

        # ---- base epilogue ----------------------------------------------------------------------------
        if temb.ndim == 3:
            shift, scale = (base.scale_shift_table.unsqueeze(0).to(temb.device) + temb.unsqueeze(2)).chunk(2, dim=2)
            shift, scale = shift.squeeze(2), scale.squeeze(2)
        else:
            shift, scale = (base.scale_shift_table.to(temb.device) + temb.unsqueeze(1)).chunk(2, dim=1)
        x = (base.norm_out(x.float()) * (1 + scale) + shift).type_as(x)
        x = base.proj_out(x)
        x = x.reshape(batch_size, ppf, pph, ppw, p_t, p_h, p_w, -1)
        x = x.permute(0, 7, 1, 4, 2, 5, 3, 6)
        return x.flatten(6, 7).flatten(4, 5).flatten(2, 3)


def build_camera_wan(base_config: dict[str, Any], control_config: CameraControlConfig | None = None,
                     seed: int = 0, device: str | torch.device | None = None,
                     dtype: torch.dtype | None = None) -> CameraControlledWan:
    """A ``CameraControlledWan`` with a randomly initialised base (seeded; the global RNG is untouched)."""
    devices = [torch.device(device)] if device is not None and torch.device(device).type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        torch.manual_seed(seed)
        with torch.device(device or "cpu"):
            base = WanTransformer3DModel(**base_config)
        if dtype is not None:
            base = base.to(dtype)
        model = CameraControlledWan(base, control_config)
    return model.eval()


def tiny_camera_wan(seed: int = 0) -> CameraControlledWan:
    """Random tiny Wan2.1 I2V base (2 heads × 12, 2 layers) + zero-initialised camera control (eval mode)."""
    return build_camera_wan(TINY_I2V_CONFIG, tiny_camera_config(), seed=seed)


@torch.no_grad()
def randomize_camera_control(model: CameraControlledWan, seed: int = 0, std: float = 0.05) -> CameraControlledWan:
    """Fill every camera-control weight with seeded ``N(0, std²)`` noise (tests and benchmarks: makes every
    control path active, which zero initialisation does not)."""
    g = torch.Generator().manual_seed(seed)
    for p in model.control.parameters():
        p.copy_((torch.randn(p.shape, generator=g) * std).to(p.dtype))
    return model
