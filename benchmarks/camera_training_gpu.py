"""GPU check of Module I at Wan2.1-1.3B width: one training step and one sampling step, 81 frames at 256², bf16.

    python benchmarks/camera_training_gpu.py --out benchmarks/results/camera-training-gpu

Random weights (timing and memory only): the base at Wan2.1-1.3B width with the I2V inputs and the camera control
of ``wan_1_3b_camera_config`` (low-rank projections). The training step is the trainer's own (``flow_loss`` +
backward + AdamW on the control, base frozen, bf16 autocast, gradient checkpointing); the sampling step is one
DiT call on a classifier-free-guidance pair (batch 2), as the sampler makes 40 of per clip. Writes
``results.json`` and ``results.md``; reports the ratio training step / sampling step besides the absolute GPU
times (GPU times are the point of this check). Needs CUDA; refuses otherwise.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch


def _clip(T: int = 81, H: int = 256, W: int = 256) -> dict:
    """A synthetic stored clip at the paper's size (latents 16 x 21 x 32 x 32; a slow sideways dolly)."""
    rng = np.random.default_rng(0)
    F, h, w = (T - 1) // 4 + 1, H // 8, W // 8
    c2w = np.tile(np.eye(4), (T, 1, 1))
    c2w[:, 0, 3] = np.linspace(0, 0.5, T)
    K = np.tile(np.array([[0.8 * W, 0, W / 2], [0, 0.8 * H, H / 2], [0, 0, 1.0]]), (T, 1, 1))
    lat = rng.standard_normal((16, F, h, w)).astype(np.float32)
    image = np.concatenate([lat[:, :1], np.zeros_like(lat[:, 1:])], axis=1)
    return {"latents": lat, "image_latents": image, "image_embeds": rng.standard_normal((257, 1280)).astype(np.float32),
            "text_embeds": rng.standard_normal((512, 4096)).astype(np.float32), "c2w": c2w, "K": K,
            "render_latents": rng.standard_normal((16, F, h, w)).astype(np.float32),
            "visibility": np.ones((T, H, W), np.uint8), "attrs": {"clip_id": "synthetic"}}


def _time(fn, repeats: int) -> tuple[float, float]:
    torch.cuda.synchronize()
    torch.cuda.reset_peak_memory_stats()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), torch.cuda.max_memory_allocated() / 2**30


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    if not torch.cuda.is_available():
        print("camera_training_gpu.py needs a CUDA GPU (none found); the CPU benchmark is "
              "benchmarks/camera_training.py", file=sys.stderr)
        return 2
    from navcrafter.models.synthesis.camcontrol import (
        build_camera_wan,
        control_parameter_counts,
        wan_1_3b_camera_config,
    )
    from navcrafter.models.synthesis.training import CameraTrainer, clip_conditions, trainable_parameters
    from navcrafter.schemas.training import CameraTrainingConfig

    base_cfg, control_cfg = wan_1_3b_camera_config()
    model = build_camera_wan(base_cfg, control_cfg, device="cuda", dtype=torch.bfloat16)
    # fp32 master weights of the control, bf16 frozen base (autocast computes in bf16)
    model.control.float()
    config = CameraTrainingConfig(text_dropout=0.0, gradient_checkpointing=True,
                                  mixed_precision="bf16")
    clip = _clip()
    trainer = CameraTrainer(model, [clip], config, device="cuda")
    train_s, train_gib = _time(trainer.train_step, args.repeats + 1)

    model.eval()
    c = clip_conditions(model, clip, "cuda")
    pair = {k: (torch.cat([v, v]) if isinstance(v, torch.Tensor) else v) for k, v in c.items()}
    x = torch.randn_like(pair["x0"])

    @torch.no_grad()
    def sample_step():
        with torch.autocast("cuda", dtype=torch.bfloat16):
            model(torch.cat([x, pair["hidden_cond"]], 1), torch.full((2,), 500.0, device="cuda"), pair["text"],
                  pair["image"], pair["plucker"], pair["cond"], torch.tensor(0.7, device="cuda"),
                  image_reference=pair["x0"][:, :, :1], image_reference_plucker=pair["plucker"][:, :, :1])

    sample_s, sample_gib = _time(sample_step, args.repeats + 1)
    counts = control_parameter_counts(base_cfg, control_cfg)
    results = {"device": torch.cuda.get_device_name(0), "frames": 81, "resolution": 256, "dtype": "bf16",
               "train_step_s": train_s, "train_peak_gib": train_gib, "sample_step_cfg_pair_s": sample_s,
               "sample_peak_gib": sample_gib, "train_over_sample": train_s / sample_s,
               "trainable_parameters": trainable_parameters(model, config), "parameter_counts": counts}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    md = "\n".join(["# Module I on a GPU: Wan2.1-1.3B width, 81 × 256², bf16 (random weights)", "",
                    f"Device: {results['device']}.", "", "| step | median time | peak memory |", "|---|---|---|",
                    f"| training (flow loss + backward + AdamW, control only, grad. checkpointing) | {train_s:.3f} s | "
                    f"{train_gib:.1f} GiB |",
                    f"| sampling (one DiT call, CFG pair) | {sample_s:.3f} s | {sample_gib:.1f} GiB |", "",
                    f"A training step takes {train_s / sample_s:.2f}× a sampling step; a 40-step clip ≈ "
                    f"{40 * sample_s:.1f} s of DiT time. Trainable parameters: "
                    f"{results['trainable_parameters']:,}.", ""])
    (args.out / "results.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
