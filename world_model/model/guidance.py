"""Guidance: classifier-free guidance (cameras) and Adaptive Projected Guidance (LiDAR), §4.1.

APG (Sadat et al. 2025, "Eliminating oversaturation and artifacts of high guidance scales")
works on the denoised prediction D = predict_x0(x_t, v, t). With the guidance direction
diff = D_cond - D_uncond, it

1. adds negative momentum: running = diff + momentum * running; diff = running;
2. caps the norm: diff *= min(1, r / ||diff||);
3. splits diff into the part parallel to D_cond and the orthogonal rest and keeps the parallel
   part only with weight eta (the parallel part is what oversaturates images, or for range maps
   shifts depths globally);
4. returns D_cond + (scale - 1) * (diff_orth + eta * diff_par).

Norms and projections are per sample over ``dims`` (default: the last three, (C, h, w) of a frame).
"""

from __future__ import annotations

import torch


def cfg_combine(v_cond: torch.Tensor, v_uncond: torch.Tensor, scale: float) -> torch.Tensor:
    """Classifier-free guidance: v_u + scale (v_c - v_u)."""
    return v_uncond + scale * (v_cond - v_uncond)


def project(v0: torch.Tensor, v1: torch.Tensor, dims: tuple[int, ...]) -> tuple[torch.Tensor, torch.Tensor]:
    """Split v0 into its components parallel and orthogonal to v1 (per sample over ``dims``)."""
    dtype = v0.dtype
    v0, v1 = v0.double(), v1.double()
    unit = v1 / v1.pow(2).sum(dim=dims, keepdim=True).sqrt().clamp_min(1e-12)
    par = (v0 * unit).sum(dim=dims, keepdim=True) * unit
    return par.to(dtype), (v0 - par).to(dtype)


class AdaptiveProjectedGuidance:
    """Stateful (momentum) APG on denoised predictions; one instance per sampling run."""

    def __init__(
        self,
        scale: float,
        eta: float = 0.0,
        norm_threshold: float = 0.0,
        momentum: float = 0.0,
        dims: tuple[int, ...] = (-1, -2, -3),
    ) -> None:
        self.scale, self.eta, self.norm_threshold, self.momentum, self.dims = (
            scale,
            eta,
            norm_threshold,
            momentum,
            dims,
        )
        self.running: torch.Tensor | None = None

    def reset(self) -> None:
        self.running = None

    def __call__(self, pred_cond: torch.Tensor, pred_uncond: torch.Tensor) -> torch.Tensor:
        diff = pred_cond - pred_uncond
        if self.momentum != 0.0:
            self.running = diff if self.running is None else diff + self.momentum * self.running
            diff = self.running
        if self.norm_threshold > 0.0:
            norm = diff.pow(2).sum(dim=self.dims, keepdim=True).sqrt()
            diff = diff * torch.clamp(self.norm_threshold / norm.clamp_min(1e-12), max=1.0)
        par, orth = project(diff, pred_cond, self.dims)
        return pred_cond + (self.scale - 1.0) * (orth + self.eta * par)
