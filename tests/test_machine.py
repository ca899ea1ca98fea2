"""The memory a process may use, read from a control-group tree written here (the real
files' layouts: cgroup v2 ``0::/path`` and v1 ``N:memory:/path``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from sq_mitsuba.machine import (
    LaunchRanks,
    available_memory,
    launch_ranks,
    memory_text,
    narrow_to_local_gpu,
    too_much_memory,
)

GIB = 2**30


def _physical() -> int:
    import os

    return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def _tree(tmp_path: Path, groups: str, files: dict[str, str]) -> tuple[Path, Path]:
    cgroup_file = tmp_path / "cgroup"
    cgroup_file.write_text(groups)
    root = tmp_path / "fs"
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text + "\n")
    return cgroup_file, root


def test_no_limit_is_the_physical_memory(tmp_path):
    cgroup_file, root = _tree(tmp_path, "0::/\n", {"memory.max": "max"})
    assert available_memory(cgroup_file, root) == _physical()
    assert available_memory(tmp_path / "absent", tmp_path / "absent") == _physical()


@pytest.mark.parametrize("groups, files, limit", [
    # A container: the root group's limit (cgroup v2).
    ("0::/\n", {"memory.max": str(GIB)}, GIB),
    # A SLURM job: its own group lower than the root's; a "max" between them is no limit.
    ("0::/slurm/uid_0/job_7/\n", {"memory.max": "max", "slurm/uid_0/job_7/memory.max":
                                  str(3 * GIB)}, 3 * GIB),
    # cgroup v1: the memory controller's line, other controllers ignored.
    ("12:cpu,cpuacct:/job\n4:memory:/job\n", {"memory/job/memory.limit_in_bytes":
                                                str(2 * GIB)}, 2 * GIB),
    # The lower of two limits wins, whichever level holds it.
    ("0::/a\n", {"memory.max": str(GIB), "a/memory.max": str(5 * GIB)}, GIB),
])
def test_the_lowest_limit_wins(tmp_path, groups, files, limit):
    cgroup_file, root = _tree(tmp_path, groups, files)
    assert available_memory(cgroup_file, root) == min(limit, _physical())


def test_an_unreadable_or_odd_cgroup_list_is_no_limit(tmp_path):
    cgroup_file, root = _tree(tmp_path, "garbage without colons\n\n", {"memory.max": "max"})
    assert available_memory(cgroup_file, root) == _physical()


@pytest.mark.parametrize("count, text", [
    (0, "0 B"), (1023, "1023 B"), (1024, "1 KiB"), (1536, "1.5 KiB"), (256 * 1024, "256 KiB"),
    (3 * GIB // 2, "1.5 GiB"), (537 * GIB, "537 GiB"), (5 * 2**40, "5 TiB"),
    (3000 * 2**40, "3e+03 TiB"),
])
def test_memory_text(count, text):
    assert memory_text(count) == text


def test_the_refusal_is_one_line_naming_need_memory_and_advice():
    line = too_much_memory("image a.png: 10 x 10 px", 3 * GIB, GIB, "scale it down")
    assert line == ("image a.png: 10 x 10 px needs about 3 GiB of memory, more than the 1 GiB "
                    "this process may use; scale it down")


@pytest.mark.parametrize(("environ", "kept", "visible"), [
    ({"WORLD_SIZE": "4", "LOCAL_RANK": "2"}, "2", "2"),             # every GPU: the r-th
    ({"WORLD_SIZE": "4", "LOCAL_RANK": "1", "CUDA_VISIBLE_DEVICES": "4,5,6,7"}, "5", "5"),
    ({"WORLD_SIZE": "2", "LOCAL_RANK": "0", "CUDA_VISIBLE_DEVICES": "GPU-a, GPU-b"}, "GPU-a",
     "GPU-a"),                                                         # UUIDs, spaces
    ({"WORLD_SIZE": "2", "LOCAL_RANK": "1", "CUDA_VISIBLE_DEVICES": "3"}, None, "3"),  # one
    ({"WORLD_SIZE": "4", "LOCAL_RANK": "3", "CUDA_VISIBLE_DEVICES": "0,1"}, None, "0,1"),
    ({"WORLD_SIZE": "1", "LOCAL_RANK": "0"}, None, None),             # one process
    ({"LOCAL_RANK": "1"}, None, None),                                 # not torchrun's
    ({"WORLD_SIZE": "2"}, None, None),
])
def test_each_torchrun_process_keeps_its_own_gpu(environ, kept, visible, tmp_path):
    """Dr.Jit renders on the first visible GPU: each process must see its own alone."""
    environ = dict(environ)
    assert narrow_to_local_gpu(environ, tmp_path / "no_driver") == kept
    assert environ.get("CUDA_VISIBLE_DEVICES") == visible


def test_a_rank_past_the_machines_gpus_is_left_to_torchs_error(tmp_path):
    """Four processes on a machine of two GPUs: ranks 2 and 3 are not pointed at GPUs that do
    not exist (they trained on the CPU beside the others' nccl); torch's own error names
    the missing device."""
    gpus = tmp_path / "gpus"
    for address in ("0000:17:00.0", "0000:65:00.0"):
        (gpus / address).mkdir(parents=True)
    for rank, kept in (("1", "1"), ("2", None)):
        environ = {"WORLD_SIZE": "4", "LOCAL_RANK": rank}
        assert narrow_to_local_gpu(environ, gpus) == kept
        assert environ.get("CUDA_VISIBLE_DEVICES") == kept


def test_launch_ranks_read_torchruns_variables():
    assert launch_ranks({}) == LaunchRanks(0, 1, 0, 1) and not launch_ranks({}).distributed
    ranks = launch_ranks({"RANK": "5", "WORLD_SIZE": "8", "LOCAL_RANK": "1",
                          "LOCAL_WORLD_SIZE": "4"})
    assert ranks == LaunchRanks(5, 8, 1, 4) and ranks.distributed
    # LOCAL_WORLD_SIZE unset: every process on this machine; empty values: unset.
    assert launch_ranks({"WORLD_SIZE": "2", "RANK": "1", "LOCAL_RANK": "1"}).local_size == 2
    assert launch_ranks({"RANK": "", "WORLD_SIZE": " "}) == LaunchRanks()
    assert launch_ranks({"RANK": "3", "LOCAL_RANK": "1"}) == LaunchRanks()  # one process


@pytest.mark.parametrize("environ, message", [
    ({"WORLD_SIZE": "2", "LOCAL_RANK": "first"},
     "LOCAL_RANK: expected an integer >= 0 (set by the launcher, e.g. torchrun), got 'first'"),
    ({"RANK": "-1", "WORLD_SIZE": "2"}, "RANK: expected an integer >= 0"),
    ({"RANK": "one"}, "RANK: expected an integer >= 0"),  # malformed even for one process
    ({"WORLD_SIZE": "0"}, "WORLD_SIZE: expected an integer >= 1"),
    ({"WORLD_SIZE": "2.5"}, "WORLD_SIZE: expected an integer >= 1"),
    ({"RANK": "4", "WORLD_SIZE": "4"}, "RANK and WORLD_SIZE: rank 4 of 4 processes"),
    ({"WORLD_SIZE": "4", "LOCAL_RANK": "2", "LOCAL_WORLD_SIZE": "2"},
     "LOCAL_RANK and LOCAL_WORLD_SIZE: rank 2 of 2 processes"),
])
def test_launch_ranks_refuse_malformed_variables_in_one_line(environ, message):
    with pytest.raises(ValueError) as error:
        launch_ranks(environ)
    assert str(error.value).startswith(message) and "\n" not in str(error.value)
    if "LOCAL" in message:  # the GPU choice reads them through the same check
        with pytest.raises(ValueError, match=message.split(":")[0]):
            narrow_to_local_gpu(dict(environ), Path("/nonexistent"))


@pytest.mark.parametrize("limit_name", ["RLIMIT_AS", "RLIMIT_DATA"])
def test_the_process_own_limit_counts(tmp_path, limit_name):
    """Under ``ulimit -v`` (or ``-d``) every memory check passed on the machine's memory and
    the work then failed inside torch's allocator: the process's own limit is a limit."""
    import subprocess
    import sys

    resource = pytest.importorskip("resource")
    limit = 3 * GIB
    code = ("import resource, sys; from pathlib import Path; "
            "from sq_mitsuba.machine import available_memory; "
            f"resource.setrlimit(resource.{limit_name}, ({limit}, resource.getrlimit("
            f"resource.{limit_name})[1])); "
            "print(available_memory(Path(sys.argv[1]), Path(sys.argv[1])))")
    if resource.getrlimit(getattr(resource, limit_name))[1] not in (resource.RLIM_INFINITY,) \
            and resource.getrlimit(getattr(resource, limit_name))[1] < limit:
        pytest.skip(f"{limit_name}'s hard limit is below {limit} bytes here")
    printed = subprocess.run([sys.executable, "-c", code, str(tmp_path / "absent")],
                             capture_output=True, text=True, check=True).stdout
    assert int(printed) == min(limit, _physical())
