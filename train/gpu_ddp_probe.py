"""Run the trainer's distributed code path in ONE process (for a machine with one GPU).

``torchrun --nproc_per_node 1`` sets WORLD_SIZE=1, and the trainer then runs without a process
group, so on one GPU nothing of DistributedDataParallel, SyncBatchNorm or the nccl collectives
runs. (Two processes cannot share one GPU under nccl.) This probe makes the trainer take its
distributed path with a process group of size 1: it reports WORLD_SIZE=2 to the trainer, lets
the trainer choose the backend and call ``init_process_group`` itself, but rewrites that call
to a group of one process, and counts a group it owns as distributed. Everything else (backend
choice, SyncBatchNorm conversion, DDP wrapping, loss averaging, agreement checks, object
broadcasts, checkpoint gathering, barriers) is the trainer's own code.

Usage: python train/gpu_ddp_probe.py [train] sq-mitsuba-train-arguments...
  e.g. python train/gpu_ddp_probe.py --config train/configs/a.toml --data DS --out RUN
       --max-steps 10 --quiet
  (the leading ``train`` is optional: ``train/gpu_check.sh`` gives every launcher it, and the
  probe took it for an argument of ``train``, which refused it)
Patches the ``distributed`` property of :class:`sq_mitsuba.training.distributed.World`; a
probe, not a product.
"""

from __future__ import annotations

import os
import sys

import torch.distributed as dist


def main() -> int:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=os.environ.get("MASTER_PORT", "29517"),
                      RANK="0", LOCAL_RANK="0", WORLD_SIZE="2")
    real_init = dist.init_process_group

    def init_one(*args: object, **kwargs: object) -> None:
        backend = kwargs.get("backend", args[0] if args else None)
        print(f"probe: the trainer asked for backend {backend!r}; group of 1 process",
              flush=True)
        kwargs.update(world_size=1, rank=0)
        real_init(*args, **kwargs)

    dist.init_process_group = init_one

    from sq_mitsuba.training.distributed import World

    World.distributed = property(lambda self: self.owns_group or self.size > 1)
    from sq_mitsuba.cli import main as cli_main

    arguments = sys.argv[1:]
    return cli_main(arguments if arguments[:1] == ["train"] else ["train", *arguments])


if __name__ == "__main__":
    sys.exit(main())
