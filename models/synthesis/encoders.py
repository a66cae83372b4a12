"""The frozen encoders of camera-control training: video latents, CLIP image features, text embeddings.

``ClipEncoders`` is what the clip precompute (``tasks/training/clips.py``) needs from a model. Conventions
(numpy, float32 unless stated; no batch axis):

* ``encode_video(video [3, T, H, W] in [-1, 1]) -> latents [C, F, h, w]`` with ``C = latent_channels``,
  ``(t, s, s) = vae_stride``, ``F = (T - 1) / t + 1``, ``h = H / s``, ``w = W / s``: the **normalised** latents
  the DiT sees (for the Wan VAE: ``(z - latents_mean) / latents_std`` of the posterior mode, as the exported
  ``vae_encoder`` graph); ``decode_video`` inverts it to ``[3, T, H, W]`` in [-1, 1].
* ``image_features(image uint8 [H, W, 3]) -> [L_img, image_dim]``: the DiT's image-token input
  (``encoder_hidden_states_image``) for the conditioning frame.
* ``text_embeddings(prompt) -> [512, text_dim]``: the DiT's text input (``encoder_hidden_states``).
* ``name``: a short description recorded with every precomputed clip (a store made with other encoders is
  refused, not mixed).

Implementations:

* ``WanEncoders(components)``: the real thing over ``onnx_export.SynthesisComponents`` (Wan2.1 VAE through
  ``VaeEncoder``/``VaeDecoder``, CLIP through ``pipeline.clip_preprocess`` + ``ClipImageFeatures``, exactly as
  the sampler; text: a UMT5 encoder + tokenizer when given, else the components' precomputed embeddings of
  their ``prompt`` / ``negative_prompt``, and a clear error for any other prompt).
* ``PixelShuffleEncoders(spatial, image_dim=..., text_dim=...)``: an exactly invertible fixed transform
  standing in for a VAE in CPU benchmarks and tests (no weights): latents are the video's space-to-depth by
  ``spatial`` (``C = 3 spatial^2``, temporal stride 1 so ``F = T``); channel ``c * spatial^2 + dy * spatial + dx``
  holds colour ``c`` at offset ``(dy, dx)`` of each ``spatial x spatial`` block (``torch.pixel_unshuffle``'s
  order). With ``temporal = t > 1`` it also folds time Wan's way: frame 0 is repeated ``t`` times to form its
  own group (latent frame 0), then every ``t`` frames form one latent frame, ``F = (T - 1) / t + 1`` and
  ``C = 3 t spatial^2`` (channel ``k * 3 spatial^2 + ...`` holds frame ``k`` of the group); decoding takes the last
  copy of frame 0's group. Image features: the image average-pooled to a ``g x g`` grid (``g^2 = image_tokens``; cell
  ``(i, j)`` covers rows ``floor(i H / g) .. floor((i+1) H / g) - 1``, likewise columns), one token per cell in
  row-major order holding the cell's mean RGB mapped to [-1, 1], zero-padded to ``image_dim``. Text: zeros.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np

from navcrafter.models.synthesis.pipeline import clip_preprocess

TEXT_TOKENS = 512  # UMT5 sequence length of Wan2.1 (onnx_export.TEXT_TOKENS)


@runtime_checkable
class ClipEncoders(Protocol):
    """What the clip precompute needs from a model (conventions in the module docstring)."""

    name: str
    latent_channels: int
    vae_stride: tuple[int, int, int]  # (temporal, height, width)
    image_dim: int
    text_dim: int

    def encode_video(self, video: np.ndarray) -> np.ndarray:
        """``[3, T, H, W]`` float32 in [-1, 1] -> normalised latents ``[C, F, h, w]``."""

    def decode_video(self, latents: np.ndarray) -> np.ndarray:
        """``[C, F, h, w]`` -> ``[3, T, H, W]`` float32 in [-1, 1]."""

    def image_features(self, image: np.ndarray) -> np.ndarray:
        """uint8 ``[H, W, 3]`` -> ``[L_img, image_dim]``."""

    def text_embeddings(self, prompt: str) -> np.ndarray:
        """``prompt`` -> ``[512, text_dim]``."""


def check_video(video: np.ndarray, stride: tuple[int, int, int], who: str) -> np.ndarray:
    """``video`` as float32 ``[3, T, H, W]`` whose sizes fit ``stride``; else a ``ValueError`` with the fix."""
    v = np.asarray(video)
    if v.ndim != 4 or v.shape[0] != 3:
        raise ValueError(f"{who}.encode_video: video must be [3, T, H, W] (channels first, no batch axis), "
                         f"got shape {v.shape}")
    st, sh, sw = stride
    T, H, W = v.shape[1:]
    if (T - 1) % st or H % sh or W % sw:
        raise ValueError(f"{who}.encode_video: a {T}x{H}x{W} video does not fit the VAE stride {stride}: T must be "
                         f"{st}k+1 and H, W multiples of {sh}, {sw}; change data.num_frames / data.resolution")
    return v.astype(np.float32, copy=False)


def _check_image(image: np.ndarray, who: str) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"{who}.image_features: image must be uint8 [H, W, 3], got {img.dtype} {img.shape}")
    return img


# --------------------------------------------------------------------------------------------------
# The stand-in: exact space-to-depth
# --------------------------------------------------------------------------------------------------
class PixelShuffleEncoders:
    """Exactly invertible fixed encoders (no weights): space-to-depth latents, pooled-colour image tokens,
    zero text (module docstring)."""

    def __init__(self, spatial: int = 4, *, image_dim: int, text_dim: int, image_tokens: int = 16,
                 temporal: int = 1) -> None:
        g = int(round(np.sqrt(image_tokens)))
        if spatial < 1:
            raise ValueError(f"spatial must be >= 1, got {spatial}")
        if image_tokens < 1 or g * g != image_tokens:
            raise ValueError(f"image_tokens must be a square number (a g x g grid of cells), got {image_tokens}")
        if image_dim < 3:
            raise ValueError(f"image_dim must be >= 3 (one token holds a cell's RGB mean), got {image_dim}")
        if text_dim < 1:
            raise ValueError(f"text_dim must be >= 1, got {text_dim}")
        if temporal < 1:
            raise ValueError(f"temporal must be >= 1, got {temporal}")
        self.spatial = int(spatial)
        self.temporal = int(temporal)
        self.grid = g
        self.image_tokens = int(image_tokens)
        self.latent_channels = 3 * self.temporal * self.spatial**2
        self.vae_stride = (self.temporal, self.spatial, self.spatial)
        self.image_dim = int(image_dim)
        self.text_dim = int(text_dim)
        self.name = (f"pixelshuffle(spatial={self.spatial}, image_tokens={self.image_tokens})" if self.temporal == 1
                     else f"pixelshuffle(spatial={self.spatial}, temporal={self.temporal}, "
                          f"image_tokens={self.image_tokens})")

    def encode_video(self, video: np.ndarray) -> np.ndarray:
        v = check_video(video, self.vae_stride, "PixelShuffleEncoders")
        s, t = self.spatial, self.temporal
        _, T, H, W = v.shape
        x = v.reshape(3, T, H // s, s, W // s, s).transpose(0, 3, 5, 1, 2, 4)  # [3, dy, dx, T, h, w]
        x = np.ascontiguousarray(x.reshape(3 * s * s, T, H // s, W // s))
        if t == 1:
            return x
        x = np.concatenate([np.repeat(x[:, :1], t - 1, axis=1), x], axis=1)  # frame 0 forms its own group
        F = x.shape[1] // t
        x = x.reshape(3 * s * s, F, t, H // s, W // s).transpose(2, 0, 1, 3, 4)  # [t, 3 s s, F, h, w]
        return np.ascontiguousarray(x.reshape(t * 3 * s * s, F, H // s, W // s))

    def decode_video(self, latents: np.ndarray) -> np.ndarray:
        z = np.asarray(latents, dtype=np.float32)
        s = self.spatial
        if z.ndim != 4 or z.shape[0] != self.latent_channels:
            raise ValueError(f"PixelShuffleEncoders.decode_video: latents must be [{self.latent_channels}, F, h, w] "
                             f"(3 x spatial^2 channels), got shape {z.shape}")
        t = self.temporal
        _, F, h, w = z.shape
        if t > 1:
            z = z.reshape(t, 3 * s * s, F, h, w).transpose(1, 2, 0, 3, 4).reshape(3 * s * s, F * t, h, w)
            z = z[:, t - 1:]  # latent frame 0's group: t copies of frame 0, keep the last
        T = z.shape[1]
        x = z.reshape(3, s, s, T, h, w).transpose(0, 3, 4, 1, 5, 2)  # [3, T, h, dy, w, dx]
        return np.ascontiguousarray(x.reshape(3, T, h * s, w * s))

    def image_features(self, image: np.ndarray) -> np.ndarray:
        img = _check_image(image, "PixelShuffleEncoders")
        H, W = img.shape[:2]
        g = self.grid
        if H < g or W < g:
            raise ValueError(f"PixelShuffleEncoders.image_features: a {W}x{H} image is smaller than the {g}x{g} grid")
        x = img.astype(np.float64) / 127.5 - 1.0
        rows = (np.arange(g + 1) * H) // g
        cols = (np.arange(g + 1) * W) // g
        out = np.zeros((g * g, self.image_dim), dtype=np.float32)
        for i in range(g):
            for j in range(g):
                out[i * g + j, :3] = x[rows[i]:rows[i + 1], cols[j]:cols[j + 1]].mean(axis=(0, 1))
        return out

    def text_embeddings(self, prompt: str) -> np.ndarray:
        return np.zeros((TEXT_TOKENS, self.text_dim), dtype=np.float32)


class PCAEncoders:
    """A fitted linear autoencoder standing in for a VAE in CPU benchmarks: ``PixelShuffleEncoders``' exact patch
    vectors (``3·t·s²`` values per latent position) projected onto their top ``channels`` principal components,
    whitened (unit variance per channel, like the Wan VAE's normalised latents). Decoding maps back and
    un-shuffles; it is the least-squares best linear reconstruction of that size, not exact: report its
    reconstruction PSNR as the ceiling of anything decoded through it.

    ``PCAEncoders.fit(latents, exact, channels)``: ``latents`` an iterable of ``exact.encode_video`` outputs
    ``[3·t·s², F, h, w]`` (the training clips only). Image features and text are ``exact``'s.
    """

    def __init__(self, exact: PixelShuffleEncoders, mean: np.ndarray, basis: np.ndarray, scale: np.ndarray) -> None:
        self.exact = exact
        self.mean = np.asarray(mean, np.float64)  # [D]
        self.basis = np.asarray(basis, np.float64)  # [C, D] orthonormal rows
        self.scale = np.asarray(scale, np.float64)  # [C] standard deviation of each component
        self.latent_channels = int(self.basis.shape[0])
        self.vae_stride = exact.vae_stride
        self.image_dim, self.text_dim = exact.image_dim, exact.text_dim
        import hashlib

        digest = hashlib.sha1(np.ascontiguousarray(self.basis, np.float32).tobytes()).hexdigest()[:12]
        self.name = f"pca(channels={self.latent_channels}, basis={digest}) of {exact.name}"

    @classmethod
    def fit(cls, latents, exact: PixelShuffleEncoders, channels: int) -> PCAEncoders:
        D = exact.latent_channels
        if not 1 <= channels <= D:
            raise ValueError(f"channels must be in 1..{D}, got {channels}")
        n, s1, s2 = 0, np.zeros(D), np.zeros((D, D))
        for z in latents:
            x = np.asarray(z, np.float64).reshape(D, -1)
            n += x.shape[1]
            s1 += x.sum(1)
            s2 += x @ x.T
        if n < 2:
            raise ValueError("PCAEncoders.fit needs latents of at least one clip")
        mean = s1 / n
        cov = s2 / n - np.outer(mean, mean)
        vals, vecs = np.linalg.eigh(cov)
        order = np.argsort(vals)[::-1][:channels]
        return cls(exact, mean, vecs[:, order].T, np.sqrt(np.maximum(vals[order], 1e-12)))

    def encode_video(self, video: np.ndarray) -> np.ndarray:
        z = self.exact.encode_video(video)
        D, F, h, w = z.shape
        c = (self.basis @ (z.reshape(D, -1) - self.mean[:, None])) / self.scale[:, None]
        return c.reshape(self.latent_channels, F, h, w).astype(np.float32)

    def decode_video(self, latents: np.ndarray) -> np.ndarray:
        c = np.asarray(latents, np.float64)
        if c.ndim != 4 or c.shape[0] != self.latent_channels:
            raise ValueError(f"PCAEncoders.decode_video: latents must be [{self.latent_channels}, F, h, w], "
                             f"got {c.shape}")
        C, F, h, w = c.shape
        z = self.basis.T @ (c.reshape(C, -1) * self.scale[:, None]) + self.mean[:, None]
        return self.exact.decode_video(z.reshape(-1, F, h, w).astype(np.float32))

    def image_features(self, image: np.ndarray) -> np.ndarray:
        return self.exact.image_features(image)

    def text_embeddings(self, prompt: str) -> np.ndarray:
        return self.exact.text_embeddings(prompt)


# --------------------------------------------------------------------------------------------------
# Wan2.1: VAE + CLIP (+ UMT5)
# --------------------------------------------------------------------------------------------------
class WanEncoders:
    """The Wan2.1 I2V encoders of ``SynthesisComponents`` (fp32 torch, ``device``), as the sampler runs them.

    Text: with ``text_encoder`` and ``tokenizer`` (UMT5 and its tokenizer, e.g. from the base folder's
    ``text_encoder/`` and ``tokenizer/``) any prompt is encoded (``onnx_export.encode_prompts``, cached per
    prompt); without, only ``components.prompt`` and ``components.negative_prompt`` are available (their
    precomputed ``components.text_embeddings``) and other prompts raise ``ValueError``.
    """

    def __init__(self, components: Any, device: str = "cpu", text_encoder: Any = None, tokenizer: Any = None) -> None:
        import torch

        # deferred: torch loads only when the Wan encoders are built
        from navcrafter.models.synthesis.onnx_export import ClipImageFeatures, VaeDecoder, VaeEncoder

        if (text_encoder is None) != (tokenizer is None):
            raise ValueError("give both text_encoder and tokenizer (UMT5 and its tokenizer), or neither")
        self.torch = torch
        self.device = torch.device(device)
        self.components = components
        vae = components.vae.config
        base = components.dit.base.config
        if base.image_dim is None:
            raise ValueError("the DiT has no image_dim (a T2V model?): camera-control training needs Wan2.1 I2V")
        self.latent_channels = int(vae.z_dim)
        self.vae_stride = (int(vae.scale_factor_temporal), int(vae.scale_factor_spatial),
                           int(vae.scale_factor_spatial))
        self.image_dim = int(base.image_dim)
        self.text_dim = int(base.text_dim)
        w = components.weights if isinstance(components.weights, dict) else {}
        self.name = f"wan2.1-i2v vae+clip ({w.get('source', 'unknown')} {w.get('path', w.get('seed', ''))})"
        self._enc = VaeEncoder(components.vae).to(self.device).eval()
        self._dec = VaeDecoder(components.vae).to(self.device).eval()
        self._clip = ClipImageFeatures(components.image_encoder).to(self.device).eval()
        self._text_encoder, self._tokenizer = text_encoder, tokenizer
        self._text: dict[str, np.ndarray] = {}
        emb = np.asarray(components.text_embeddings, dtype=np.float32)
        if text_encoder is None:
            self._text[components.negative_prompt] = emb[1]
            self._text[components.prompt] = emb[0]

    def _run(self, module, x: np.ndarray) -> np.ndarray:
        with self.torch.no_grad():
            t = self.torch.as_tensor(np.asarray(x, dtype=np.float32), device=self.device)
            return module(t).float().cpu().numpy()

    def encode_video(self, video: np.ndarray) -> np.ndarray:
        v = check_video(video, self.vae_stride, "WanEncoders")
        return self._run(self._enc, v[None])[0]

    def decode_video(self, latents: np.ndarray) -> np.ndarray:
        z = np.asarray(latents, dtype=np.float32)
        if z.ndim != 4 or z.shape[0] != self.latent_channels:
            raise ValueError(f"WanEncoders.decode_video: latents must be [{self.latent_channels}, F, h, w], "
                             f"got shape {z.shape}")
        return self._run(self._dec, z[None])[0]

    def image_features(self, image: np.ndarray) -> np.ndarray:
        img = _check_image(image, "WanEncoders")
        return self._run(self._clip, clip_preprocess(img, self.components.image_preprocess))[0]

    def text_embeddings(self, prompt: str) -> np.ndarray:
        if prompt not in self._text:
            if self._text_encoder is None:
                raise ValueError(
                    f"WanEncoders has text embeddings only for the components' prompt {self.components.prompt!r} "
                    f"(and negative prompt), not {prompt!r}: load the components with that prompt "
                    f"(onnx_export.load_components(base, prompt=...)), or pass text_encoder= and tokenizer= "
                    f"(UMT5 from the base folder) to encode any prompt")
            # deferred: torch loads only when prompts are encoded
            from navcrafter.models.synthesis.onnx_export import encode_prompts

            self._text[prompt] = encode_prompts(self._text_encoder, self._tokenizer, [prompt])[0]
        return self._text[prompt]
