"""What this machine lets a process use, for the checks that refuse work it cannot do, and
where the process stands in a multi-process run (:func:`launch_ranks`).

Every command that could ask for more memory than there is (a dataset render at a large
resolution, depth fusion, a fit, a large image to predict) estimates its need first and
compares it with :func:`available_memory`, so an absurd size fails at once with one line
instead of being killed for memory after minutes.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, MutableMapping
from dataclasses import dataclass
from pathlib import Path

#: Where Linux says which control groups this process is in, and where their limits are.
CGROUP_FILE = Path("/proc/self/cgroup")
CGROUP_ROOT = Path("/sys/fs/cgroup")


def _physical_memory() -> int | None:
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _cgroup_limit_files(cgroup_file: Path, root: Path) -> list[Path]:
    """The memory-limit files that may bound this process: the root group's (a container's)
    and its own group's (a SLURM job's), for cgroup v2 (``0::/path``) and v1
    (``N:memory:/path``)."""
    files = [root / "memory.max", root / "memory" / "memory.limit_in_bytes"]
    try:
        lines = cgroup_file.read_text().splitlines()
    except OSError:
        return files
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, group = parts
        group = group.strip().strip("/")
        if controllers == "":
            files.append(root / group / "memory.max")
        elif "memory" in controllers.split(","):
            files.append(root / "memory" / group / "memory.limit_in_bytes")
    return files


def _resource_limits() -> list[int]:
    """The process's own limits on its memory (``ulimit -v`` and ``-d``), where set."""
    try:
        import resource
    except ImportError:  # not on Windows
        return []
    limits = []
    for name in ("RLIMIT_AS", "RLIMIT_DATA"):
        try:
            soft, _ = resource.getrlimit(getattr(resource, name))
        except (AttributeError, ValueError, OSError):
            continue
        if soft != resource.RLIM_INFINITY and soft > 0:
            limits.append(int(soft))
    return limits


def available_memory(cgroup_file: Path = CGROUP_FILE, root: Path = CGROUP_ROOT) -> int | None:
    """Bytes of memory this process may use: the machine's physical memory, or a control
    group's limit (a container's, a SLURM job's) or the process's own limit (``ulimit -v``,
    ``ulimit -d``) where lower; None where none is known.

    Convention: what the process may use, not what is free now: a check against the memory
    other programs happen to hold would refuse a run one minute and take it the next.

    Args:
        cgroup_file: the process's list of control groups (``/proc/self/cgroup``).
        root: where the control groups' files are mounted (``/sys/fs/cgroup``).
    """
    limits = _resource_limits()
    if (physical := _physical_memory()) is not None:
        limits.append(physical)
    for path in _cgroup_limit_files(cgroup_file, root):
        try:
            text = path.read_text().strip()
        except OSError:
            continue
        if text.isdigit():  # "max" (v2) means no limit
            limits.append(int(text))
    return min(limits) if limits else None


def memory_text(count: float) -> str:
    """Bytes as people read them, in binary units: ``"512 B"``, ``"1.5 GiB"``, ``"3.2 TiB"``.

    Convention: three significant digits, the largest unit that keeps the number >= 1.
    """
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(count) < 1024 or unit == "TiB":
            return f"{count:.0f} B" if unit == "B" else f"{count:.3g} {unit}"
        count /= 1024
    raise AssertionError("unreachable")


def too_much_memory(what: str, need: int, memory: int, advice: str) -> str:
    """The one-line refusal every memory check gives: ``"{what} needs about N of memory,
    more than the M this process may use; {advice}"``."""
    return (f"{what} needs about {memory_text(need)} of memory, more than the "
            f"{memory_text(memory)} this process may use; {advice}")


#: One folder per NVIDIA GPU the driver sees (Linux): a count that does not start CUDA.
NVIDIA_GPUS = Path("/proc/driver/nvidia/gpus")


@dataclass(frozen=True)
class LaunchRanks:
    """This process's place in a multi-process run, as its launcher (torchrun) describes it in
    the environment: ``rank`` of ``size`` processes in all (``RANK``, ``WORLD_SIZE``), and
    ``local_rank`` of ``local_size`` on this machine (``LOCAL_RANK``, ``LOCAL_WORLD_SIZE``).
    One process alone: 0 of 1, 0 of 1."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0
    local_size: int = 1

    @property
    def distributed(self) -> bool:
        return self.size > 1


def launch_ranks(environ: Mapping[str, str] = os.environ) -> LaunchRanks:
    """The launcher's ranks from ``environ`` (an unset or empty variable: one process's value;
    ``LOCAL_WORLD_SIZE`` unset: ``WORLD_SIZE``, every process on this machine; ``WORLD_SIZE``
    unset or 1: one process, rank 0, whatever ranks another launcher set).

    Raises:
        ValueError: one line naming the variable: not an integer, negative, a size below 1, or
            a rank not below its size.
    """
    def read(name: str, default: int, low: int) -> int:
        text = environ.get(name, "").strip()
        if not text:
            return default
        try:
            value = int(text)
        except ValueError:
            value = low - 1
        if value < low:
            raise ValueError(f"{name}: expected an integer >= {low} (set by the launcher, e.g. "
                             f"torchrun), got {environ[name]!r}")
        return value

    size = read("WORLD_SIZE", 1, 1)
    ranks = LaunchRanks(read("RANK", 0, 0), size, read("LOCAL_RANK", 0, 0),
                        read("LOCAL_WORLD_SIZE", size, 1))
    if not ranks.distributed:  # one process is rank 0, whatever another launcher left set
        return LaunchRanks()
    for rank, total, names in ((ranks.rank, ranks.size, "RANK and WORLD_SIZE"),
                               (ranks.local_rank, ranks.local_size,
                                "LOCAL_RANK and LOCAL_WORLD_SIZE")):
        if rank >= total:
            raise ValueError(f"{names}: rank {rank} of {total} processes (a rank lies below "
                             "its size)")
    return ranks


def narrow_to_local_gpu(environ: MutableMapping[str, str] = os.environ,
                        gpus_folder: Path = NVIDIA_GPUS) -> str | None:
    """Give each process of a multi-process run (torchrun's ``WORLD_SIZE`` > 1) its own GPU
    alone: ``CUDA_VISIBLE_DEVICES`` becomes the ``LOCAL_RANK``-th of the devices listed there
    (all when unset), so that torch and Dr.Jit both see that one device, as ``cuda:0``.

    Why: Dr.Jit 1.x has no call that chooses a CUDA device; it renders on the first visible
    one, so without this every process would render on GPU 0 while its network ran on GPU r.
    Call it before torch or Mitsuba first touches CUDA (the variable is read once, at CUDA's
    start); ``sq-mitsuba train`` does.

    Returns:
        The device it kept, or None where it changed nothing (one process, no LOCAL_RANK, one
        device listed already, or fewer devices listed, or fewer GPUs in ``gpus_folder``,
        than local ranks: torch's error then names the missing device, where a process given
        none would have trained on the CPU beside the others' GPUs).
    """
    ranks = launch_ranks(environ)
    if not ranks.distributed or not environ.get("LOCAL_RANK", "").strip():
        return None
    rank = ranks.local_rank
    listed = environ.get("CUDA_VISIBLE_DEVICES")
    devices = [d.strip() for d in listed.split(",") if d.strip()] if listed is not None \
        else None
    if devices is None and gpus_folder.is_dir() and rank >= len(list(gpus_folder.iterdir())):
        return None
    if devices is not None and (len(devices) <= 1 or rank >= len(devices)):
        return None
    kept = str(rank) if devices is None else devices[rank]
    environ["CUDA_VISIBLE_DEVICES"] = kept
    return kept
