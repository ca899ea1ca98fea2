"""Shared test configuration.

Tests run on 2 CPU threads (the reference machine). Fixtures that build Mitsuba scenes are
session-scoped: the first kernels compile for seconds, later renders reuse them.
"""

from __future__ import annotations

import torch

torch.set_num_threads(2)
