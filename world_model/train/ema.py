"""Exponential moving average of parameters, with the usual warm-up so short runs are usable."""

from __future__ import annotations

import torch
from torch import nn


class EMA:
    """shadow <- d * shadow + (1 - d) * param, with d = min(decay, (1 + n) / (10 + n)) at update n."""

    def __init__(self, model: nn.Module, decay: float) -> None:
        self.decay = decay
        self.updates = 0
        self.shadow = {k: p.detach().clone().float() for k, p in model.named_parameters()}

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        d = min(self.decay, (1 + self.updates) / (10 + self.updates))
        params = dict(model.named_parameters())
        shadows = list(self.shadow.values())
        torch._foreach_mul_(shadows, d)
        torch._foreach_add_(shadows, [params[k].detach().float() for k in self.shadow], alpha=1 - d)
        self.updates += 1

    def state_dict(self) -> dict[str, torch.Tensor]:
        return dict(self.shadow)

    def load_state_dict(self, state: dict[str, torch.Tensor], updates: int) -> None:
        missing = set(self.shadow) - set(state)
        if missing:
            raise KeyError(f"EMA state lacks {sorted(missing)[:3]}...")
        self.shadow = {k: state[k].to(v.device, torch.float32, copy=True) for k, v in self.shadow.items()}
        self.updates = updates

    def model_state(self, model: nn.Module) -> dict[str, torch.Tensor]:
        """The model's state dict with EMA parameters (buffers taken from the model)."""
        state = dict(model.state_dict())
        state.update({k: v.to(state[k].dtype) for k, v in self.shadow.items()})
        return state
