"""The optimiser and its learning-rate schedule: AdamW, stepped once per training step along
a linear warm-up and a cosine decay."""

from __future__ import annotations

import math

import torch
from torch import nn

from sq_mitsuba.training.config import OptimConfig

__all__ = ["cosine_lr_factor", "make_optimizer"]


def cosine_lr_factor(step: int, total_steps: int, warmup_steps: int = 0,
                     min_ratio: float = 0.0) -> float:
    """Learning-rate multiplier of step ``step`` (0-based): a linear warm-up over W =
    ``warmup_steps`` steps, 1/W, 2/W, ..., 1 (the peak held at steps W - 1 and W), then a
    cosine from 1 down to ``min_ratio`` at the last step."""
    if warmup_steps > 0 and step < warmup_steps:
        return (step + 1) / warmup_steps
    span = max(1, total_steps - 1 - warmup_steps)
    progress = min(1.0, max(0.0, (step - warmup_steps) / span))
    return min_ratio + (1.0 - min_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress))


def make_optimizer(model: nn.Module, optim: OptimConfig, total_steps: int
                   ) -> tuple[torch.optim.AdamW, torch.optim.lr_scheduler.LambdaLR]:
    """AdamW over ``model``'s trainable parameters (``requires_grad``) and its per-step
    schedule (:func:`cosine_lr_factor` over ``total_steps``), peaking at
    :meth:`OptimConfig.peak_lr` after :meth:`OptimConfig.warmup_step_count` steps, with
    :meth:`OptimConfig.adam_betas` and :meth:`OptimConfig.adam_eps` (the batch size's
    scaling)."""
    parameters = [p for p in model.parameters() if p.requires_grad]
    warmup = optim.warmup_step_count()
    optimizer = torch.optim.AdamW(parameters, lr=optim.peak_lr(), betas=optim.adam_betas(),
                                  eps=optim.adam_eps(), weight_decay=optim.weight_decay)
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda s: cosine_lr_factor(s, total_steps, warmup, optim.min_lr_ratio))
    return optimizer, scheduler
