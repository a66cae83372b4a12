"""One DDP process of camera-control training: ``torchrun ... -m navcrafter.tasks.training.worker RUN``.

Reads ``RANK``/``WORLD_SIZE``/``LOCAL_RANK`` from torchrun's environment, joins the process group (NCCL on CUDA,
gloo otherwise) and runs ``tasks.training.train.train`` on its share of every step's batch; rank 0 writes the
checkpoints. ``NAVCRAFTER_TRAIN_STEPS`` (optional) stops at that step instead of ``config.steps`` (tests).
"""

from __future__ import annotations

import os
import sys

from navcrafter.tasks.training.train import train


def main(argv: list[str]) -> int:
    import torch
    import torch.distributed as dist

    if len(argv) != 1:
        print("usage: torchrun --nproc_per_node N -m navcrafter.tasks.training.worker RUN_DIR", file=sys.stderr)
        return 2
    rank, world = int(os.environ.get("RANK", 0)), int(os.environ.get("WORLD_SIZE", 1))
    cuda = torch.cuda.is_available()
    device = f"cuda:{int(os.environ.get('LOCAL_RANK', 0))}" if cuda else "cpu"
    if cuda:
        torch.cuda.set_device(device)
    dist.init_process_group(backend="nccl" if cuda else "gloo")
    try:
        steps = os.environ.get("NAVCRAFTER_TRAIN_STEPS")
        summary = train(argv[0], rank=rank, world_size=world, device=device,
                        steps=int(steps) if steps else None)
        if rank == 0:
            print(f"trained to step {summary['steps']} on {world} processes", flush=True)
        dist.barrier()
    finally:
        dist.destroy_process_group()
    return 0


if __name__ == "__main__":
    code = main(sys.argv[1:])
    # gloo's background threads can abort the interpreter's normal teardown ("terminate called without an active
    # exception", exit -6) after the group was destroyed and every result written; leave without it.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
