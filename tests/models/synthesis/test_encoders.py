"""The training encoders: the exact pixel-shuffle stand-in and the Wan2.1 VAE/CLIP wrapper (tiny random modules)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from navcrafter.models.synthesis.encoders import TEXT_TOKENS, ClipEncoders, PixelShuffleEncoders, WanEncoders

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_pixel_shuffle_is_exactly_invertible():
    enc = PixelShuffleEncoders(4, image_dim=6, text_dim=8)
    assert isinstance(enc, ClipEncoders)
    assert (enc.latent_channels, enc.vae_stride) == (48, (1, 4, 4))
    rng = np.random.default_rng(0)
    video = rng.uniform(-1, 1, (3, 5, 8, 12)).astype(np.float32)
    z = enc.encode_video(video)
    assert z.shape == (48, 5, 2, 3) and z.dtype == np.float32
    np.testing.assert_array_equal(enc.decode_video(z), video)  # bit for bit
    # channel c * s^2 + dy * s + dx holds colour c at offset (dy, dx): torch.pixel_unshuffle's order
    ref = torch.pixel_unshuffle(torch.from_numpy(video).permute(1, 0, 2, 3), 4).permute(1, 0, 2, 3).numpy()
    np.testing.assert_array_equal(z, ref)
    # any latents decode and re-encode exactly too (a bijection)
    lat = rng.standard_normal((48, 3, 4, 2)).astype(np.float32)
    np.testing.assert_array_equal(enc.encode_video(enc.decode_video(lat)), lat)
    one = PixelShuffleEncoders(1, image_dim=3, text_dim=1)
    np.testing.assert_array_equal(one.decode_video(one.encode_video(video)), video)


def test_pixel_shuffle_image_tokens_and_text():
    enc = PixelShuffleEncoders(2, image_dim=5, text_dim=7, image_tokens=4)
    img = np.zeros((6, 10, 3), dtype=np.uint8)  # 2x2 grid: rows 0-2 | 3-5, columns 0-4 | 5-9
    img[:3, :5] = (255, 0, 0)
    img[3:, 5:] = (0, 255, 127)
    f = enc.image_features(img)
    assert f.shape == (4, 5) and f.dtype == np.float32
    np.testing.assert_allclose(f[:, :3], [[1, -1, -1], [-1, -1, -1], [-1, -1, -1], [-1, 1, 127 / 127.5 - 1]],
                               atol=1e-6)
    np.testing.assert_array_equal(f[:, 3:], 0)  # zero padding
    assert enc.image_features(np.full((7, 9, 3), 128, np.uint8)).shape == (4, 5)  # sizes not divisible
    t = enc.text_embeddings("a room")
    assert t.shape == (TEXT_TOKENS, 7) and not t.any()


def test_pixel_shuffle_errors():
    enc = PixelShuffleEncoders(4, image_dim=4, text_dim=4)
    with pytest.raises(ValueError, match="multiples of 4"):
        enc.encode_video(np.zeros((3, 5, 10, 8), np.float32))
    with pytest.raises(ValueError, match=r"\[3, T, H, W\]"):
        enc.encode_video(np.zeros((1, 3, 5, 8, 8), np.float32))
    with pytest.raises(ValueError, match="48"):
        enc.decode_video(np.zeros((16, 5, 2, 2), np.float32))
    with pytest.raises(ValueError, match="uint8"):
        enc.image_features(np.zeros((8, 8, 3), np.float32))
    with pytest.raises(ValueError, match="square number"):
        PixelShuffleEncoders(4, image_dim=4, text_dim=4, image_tokens=12)
    with pytest.raises(ValueError, match="image_dim"):
        PixelShuffleEncoders(4, image_dim=2, text_dim=4)


@pytest.fixture(scope="module")
def tiny():
    from navcrafter.models.synthesis.onnx_export import tiny_components

    return tiny_components(seed=0, prompt="a room")


def test_wan_encoders_match_the_sampler(tiny):
    from navcrafter.models.synthesis.pipeline import TorchRunner, clip_preprocess

    enc = WanEncoders(tiny)
    assert isinstance(enc, ClipEncoders)
    assert (enc.latent_channels, enc.vae_stride) == (16, (4, 8, 8))
    assert (enc.image_dim, enc.text_dim) == (tiny.dit.base.config.image_dim, tiny.dit.base.config.text_dim)
    rng = np.random.default_rng(1)
    video = rng.uniform(-1, 1, (3, 5, 16, 16)).astype(np.float32)
    z = enc.encode_video(video)
    assert z.shape == (16, 2, 2, 2) and z.dtype == np.float32
    runner = TorchRunner(tiny)
    np.testing.assert_allclose(z, runner.vae_encode(video[None])[0], rtol=1e-5, atol=1e-6)
    out = enc.decode_video(z)
    assert out.shape == (3, 5, 16, 16) and np.abs(out).max() <= 1.0
    image = rng.integers(0, 256, (24, 40, 3), dtype=np.uint8)
    feats = enc.image_features(image)
    ref = runner.encode_image_clip(clip_preprocess(image, tiny.image_preprocess))[0]
    assert feats.shape == ref.shape and feats.shape[1] == enc.image_dim
    np.testing.assert_allclose(feats, ref, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(enc.text_embeddings("a room"), tiny.text_embeddings[0])
    np.testing.assert_array_equal(enc.text_embeddings(tiny.negative_prompt), tiny.text_embeddings[1])
    with pytest.raises(ValueError, match="load the components with that prompt"):
        enc.text_embeddings("a street")
    with pytest.raises(ValueError, match="4k\\+1"):
        enc.encode_video(np.zeros((3, 4, 16, 16), np.float32))
    with pytest.raises(ValueError, match="both text_encoder and tokenizer"):
        WanEncoders(tiny, text_encoder=object())


def test_pixel_shuffle_folds_time_the_wan_way():
    """temporal=4: frame 0 alone in latent frame 0, then 4 frames per latent frame; exactly invertible."""
    e = PixelShuffleEncoders(4, temporal=4, image_dim=8, text_dim=16)
    v = np.random.default_rng(0).uniform(-1, 1, (3, 9, 16, 16)).astype(np.float32)
    z = e.encode_video(v)
    assert z.shape == (192, 3, 4, 4) and e.vae_stride == (4, 4, 4) and e.latent_channels == 192
    assert np.array_equal(e.decode_video(z), v)
    spatial = PixelShuffleEncoders(4, image_dim=8, text_dim=16).encode_video(v)  # [48, 9, 4, 4]
    assert np.array_equal(z[:48, 0], spatial[:, 0]) and np.array_equal(z[144:, 0], spatial[:, 0])
    assert np.array_equal(z[:48, 1], spatial[:, 1]) and np.array_equal(z[144:, 2], spatial[:, 8])
    with pytest.raises(ValueError, match="4k\\+1"):
        e.encode_video(v[:, :8])
