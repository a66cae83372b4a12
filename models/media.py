"""Video files: H.264 MP4 encoding and the label burnt into the frames of labelled runs (SIMULATION, RANDOM
WEIGHTS)."""

from __future__ import annotations

import os
import tempfile

import numpy as np
from PIL import Image, ImageDraw, ImageFont


def encode_mp4(frames: np.ndarray, fps: int) -> bytes:
    """H.264 MP4 (yuv420p) of ``[T, H, W, 3]`` uint8 frames, via the ffmpeg of imageio-ffmpeg."""
    import imageio_ffmpeg

    T, H, W, _ = frames.shape
    fd, path = tempfile.mkstemp(suffix=".mp4")
    os.close(fd)
    try:
        writer = imageio_ffmpeg.write_frames(path, (W, H), fps=fps, codec="libx264", pix_fmt_out="yuv420p",
                                             quality=8, macro_block_size=1, ffmpeg_log_level="error",
                                             output_params=["-threads", "1", "-fflags", "+bitexact",
                                                            "-map_metadata", "-1"])
        writer.send(None)
        for f in frames:
            writer.send(np.ascontiguousarray(f))
        writer.close()
        with open(path, "rb") as fh:
            return fh.read()
    finally:
        os.unlink(path)


def label_frames(frames: np.ndarray, text: str = "SIMULATION") -> np.ndarray:
    """Burn a small label into the top-left corner of every frame."""
    H = frames.shape[1]
    font = ImageFont.load_default(size=max(8, H // 18))
    out = np.empty_like(frames)
    for i, f in enumerate(frames):
        im = Image.fromarray(f)
        draw = ImageDraw.Draw(im)
        box = draw.textbbox((2, 1), text, font=font)
        draw.rectangle(box, fill=(0, 0, 0))
        draw.text((2, 1), text, fill=(255, 220, 0), font=font)
        out[i] = np.asarray(im)
    return out
