"""The optimiser step every learner takes, guarded against non-finite losses."""
from __future__ import annotations

from typing import Iterable

import torch

from hvc.errors import NonFiniteLoss


def clipped_step(optimizer: torch.optim.Optimizer, loss: torch.Tensor, parameters: Iterable[torch.nn.Parameter],
                 max_norm: float = 40.0) -> None:
    """Backward, clip the gradient norm, step; a NaN or inf loss or gradient raises
    NonFiniteLoss before the step, leaving weights and optimiser moments untouched."""
    parameters = list(parameters)
    optimizer.zero_grad()
    loss.backward()
    norm = torch.nn.utils.clip_grad_norm_(parameters, max_norm)
    if not (torch.isfinite(loss) and torch.isfinite(norm)):
        raise NonFiniteLoss(f"non-finite loss {float(loss.detach())} (gradient norm {float(norm)})")
    optimizer.step()
