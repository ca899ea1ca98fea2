"""Checks shared by the end-to-end command tests (eval, predict, study)."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch
from PIL import Image


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    """Torch on one thread in a module: as fast for the tiny network, and it stays fast when
    other processes share the cores (two threads then wait for each other at every operation)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def assert_picture(path):
    """A PNG that exists, is not empty and is not a single colour."""
    assert path.is_file() and path.stat().st_size > 0, path
    with Image.open(path) as image:
        pixels = np.asarray(image.convert("RGB")).reshape(-1, 3)
    # Any pixel unlike the first (np.unique over rows sorts them all: seconds on a page).
    assert (pixels != pixels[0]).any(), f"{path} is a single colour"


def read_rows(path):
    with open(path, newline="", encoding="utf-8") as handle:
        return list(csv.DictReader(handle))


def error_line(capsys) -> str:
    """The one line a failed command printed on stderr."""
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    return lines[0]
