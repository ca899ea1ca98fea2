"""Distributed training set-up: the process group torchrun describes, the collective helpers
the loop uses, and BatchNorm statistics over the global batch on the CPU.

Under ``torchrun`` (``WORLD_SIZE`` > 1) process r of N takes the r-th of N equal slices of each
step's batch and renders its own items; gradients are averaged by DistributedDataParallel
(gloo on the CPU, nccl on CUDA), and BatchNorm statistics are synchronised over the global
batch (torch's SyncBatchNorm on CUDA, :class:`CpuSyncBatchNorm` on the CPU), so N processes
follow the same trajectory as one process with the same global batch, up to float rounding
(other summation orders; tested: 3 steps agree to 1e-5) and the encoder's stochastic depth,
whose random draws are per process; with ``reprojection.items`` each process renders that
many of its own slice (N x items a step in all). The CUDA path (device ``cuda``, Mitsuba's
``cuda_ad_mono`` variant, nccl) is written but untested here, and not bit-reproducible.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from sq_mitsuba.machine import launch_ranks

__all__ = [
    "CpuSyncBatchNorm",
    "World",
    "all_mean",
    "any_rank",
    "barrier",
    "broadcast_object",
    "convert_cpu_sync_batchnorm",
    "start_distributed",
    "unwrap",
    "wrap_model",
]


# torch deprecates torch.distributed.nn.functional.all_reduce for
# _functional_collectives.all_reduce (not checked here); the old one's backward sums the
# gradients over processes, as the statistics' gradient needs (input gradients equal
# BatchNorm2d's over the global batch to 3e-16 in float64, 2 processes). One filter, set
# once: a catch_warnings in forward would swap the process's filters every step.
warnings.filterwarnings("ignore", "torch.distributed.nn.functional.all_reduce is deprecated",
                        FutureWarning)


class CpuSyncBatchNorm(nn.BatchNorm2d):
    """BatchNorm2d whose training statistics span every process of a distributed run, on
    the CPU (torch's SyncBatchNorm needs a GPU).

    The per-channel sum, sum of squares and count are summed over processes with the
    autograd-aware ``torch.distributed.nn.functional.all_reduce``, whose backward sums the
    gradients likewise, so values and gradients equal those of BatchNorm over the global batch.
    Statistics are accumulated in float64. Outside a distributed run, or in eval mode, this is
    plain BatchNorm2d. The parameters and buffers are BatchNorm2d's (same state-dict keys).
    """

    def forward(self, x: Tensor) -> Tensor:
        import torch.distributed as dist

        if not (self.training and dist.is_available() and dist.is_initialized()):
            return super().forward(x)
        from torch.distributed.nn.functional import all_reduce

        channels = x.shape[1]
        dims = [0, *range(2, x.dim())]
        wide = x.to(torch.float64)
        count = wide.new_tensor([x.numel() / channels])
        packed = all_reduce(torch.cat([wide.sum(dims), (wide * wide).sum(dims), count]))
        total = packed[-1]
        mean = packed[:channels] / total
        var = (packed[channels:2 * channels] / total - mean * mean).clamp_min(0)
        if self.track_running_stats and self.running_mean is not None:
            with torch.no_grad():
                self.num_batches_tracked.add_(1)
                momentum = (1.0 / float(self.num_batches_tracked) if self.momentum is None
                            else self.momentum)
                unbiased = var * total / (total - 1).clamp_min(1)
                self.running_mean.mul_(1 - momentum).add_(momentum * mean.to(x.dtype))
                self.running_var.mul_(1 - momentum).add_(momentum * unbiased.to(x.dtype))
        shape = [1, channels] + [1] * (x.dim() - 2)
        y = ((wide - mean.view(shape)) * torch.rsqrt(var.view(shape) + self.eps)).to(x.dtype)
        if self.affine:
            y = y * self.weight.view(shape) + self.bias.view(shape)
        return y


def convert_cpu_sync_batchnorm(module: nn.Module) -> nn.Module:
    """Replace every BatchNorm2d of ``module`` by a :class:`CpuSyncBatchNorm` with its state,
    its very parameters included (as torch's ``SyncBatchNorm.convert_sync_batchnorm``): a
    frozen layer's stay frozen (``optim.trainable``), and an optimiser sees the same ones."""
    for name, child in module.named_children():
        if isinstance(child, nn.BatchNorm2d) and not isinstance(child, CpuSyncBatchNorm):
            sync = CpuSyncBatchNorm(child.num_features, child.eps, child.momentum,
                                    child.affine, child.track_running_stats)
            sync.load_state_dict(child.state_dict())
            if child.affine:
                sync.weight, sync.bias = child.weight, child.bias
            sync.train(child.training)
            setattr(module, name, sync)
        else:
            convert_cpu_sync_batchnorm(child)
    return module


@dataclass(frozen=True)
class World:
    """This process's place in a (possibly one-process) training run."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0
    owns_group: bool = False

    @property
    def main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.size > 1

    @property
    def local_size(self) -> int:
        """Processes of the run on this machine (torchrun's ``LOCAL_WORLD_SIZE``), which share
        its cores (on several nodes, fewer than ``size``)."""
        return launch_ranks().local_size if self.distributed else 1


def start_distributed(device: torch.device) -> World:
    """Join the process group torchrun describes (``WORLD_SIZE`` > 1); else one process."""
    launch = launch_ranks()
    if not launch.distributed:
        return World()
    import torch.distributed as dist

    owns = False
    if not dist.is_initialized():
        if device.type == "cuda":
            torch.cuda.set_device(device)  # object collectives and barriers use this GPU
        # nccl takes CUDA tensors only; the loss means and flags are CPU tensors (gloo).
        dist.init_process_group(backend="cpu:gloo,cuda:nccl" if device.type == "cuda"
                                else "gloo")
        owns = True
    return World(dist.get_rank(), dist.get_world_size(), launch.local_rank, owns)


def all_mean(values: Tensor, world: World) -> Tensor:
    """The mean of ``values`` over every process (``values`` itself in a one-process run)."""
    if not world.distributed:
        return values
    import torch.distributed as dist

    values = values.clone()
    dist.all_reduce(values)
    return values / world.size


def any_rank(flag: bool, world: World) -> bool:
    """Whether ``flag`` holds on any process."""
    if not world.distributed:
        return flag
    import torch.distributed as dist

    value = torch.tensor([1.0 if flag else 0.0])
    dist.all_reduce(value, op=dist.ReduceOp.MAX)
    return bool(value.item() > 0)


def barrier(world: World) -> None:
    """Wait for every process."""
    if world.distributed:
        import torch.distributed as dist

        dist.barrier()


def broadcast_object(value: Any, world: World) -> Any:
    """Rank 0's ``value`` on every rank."""
    if not world.distributed:
        return value
    import torch.distributed as dist

    box = [value]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def wrap_model(model: nn.Module, device: torch.device, world: World) -> nn.Module:
    """``model`` ready for ``world``: BatchNorm synchronised over processes and wrapped in
    DistributedDataParallel when there are several; ``model`` itself otherwise."""
    if not world.distributed:
        return model
    if device.type == "cuda":
        model = nn.SyncBatchNorm.convert_sync_batchnorm(model)
    else:
        model = convert_cpu_sync_batchnorm(model)
    with warnings.catch_warnings():
        # broadcast_buffers=False is deprecated for forward_sync_buffers=False, which still
        # syncs at the start; the running statistics are each process's own (from one seed).
        warnings.filterwarnings("ignore", "`broadcast_buffers` is deprecated", FutureWarning)
        return nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None,
            broadcast_buffers=False, find_unused_parameters=True)


def unwrap(model: nn.Module) -> nn.Module:
    """The network inside a DistributedDataParallel wrapper (``model`` itself otherwise)."""
    return model.module if hasattr(model, "module") else model
