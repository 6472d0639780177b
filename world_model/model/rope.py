"""3-D rotary position embedding over (frame, row, col) of each view's token grid (§3.2).

The head dimension is split into three even parts, one per axis (rows and columns get
``2 * (head_dim // 6)`` each, frames the rest), each rotated with its own positions. Frame
positions start at ``frame_offset`` so a streaming engine can continue a rollout with cached
keys of earlier frames (their keys were rotated with their own absolute frame index).
"""

from __future__ import annotations

import torch


def rope_axis_dims(head_dim: int) -> tuple[int, int, int]:
    """(frame, row, col) sizes of the head dimension; all even, summing to ``head_dim``."""
    spatial = 2 * (head_dim // 6)
    return head_dim - 2 * spatial, spatial, spatial


def _angles(pos: torch.Tensor, dim: int, theta: float) -> torch.Tensor:
    inv = 1.0 / theta ** (torch.arange(0, dim, 2, dtype=torch.float64, device=pos.device) / dim)
    return pos.double()[:, None] * inv[None, :]


def rope_tables(
    head_dim: int,
    frames: int,
    rows: int,
    cols: int,
    frame_offset: int = 0,
    theta: float = 10000.0,
    device: torch.device | str = "cpu",
) -> tuple[torch.Tensor, torch.Tensor]:
    """cos, sin of shape (frames * rows * cols, head_dim / 2) on ``device``, tokens ordered (frame, row, col)."""
    df, dr, dc = rope_axis_dims(head_dim)
    f = torch.arange(frames, device=device) + frame_offset
    r = torch.arange(rows, device=device)
    c = torch.arange(cols, device=device)
    ff, rr, cc = (g.reshape(-1) for g in torch.meshgrid(f, r, c, indexing="ij"))
    ang = torch.cat([_angles(ff, df, theta), _angles(rr, dr, theta), _angles(cc, dc, theta)], dim=1)
    return ang.cos().float(), ang.sin().float()


def rotation_tables(cos: torch.Tensor, sin: torch.Tensor, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Half tables (S, head_dim / 2) -> the full (S, head_dim) tables :func:`apply_rope` takes:
    ``[cos, cos]`` and ``[-sin, sin]``, in ``dtype``. Built once per forward, shared by every layer."""
    return torch.cat([cos, cos], dim=-1).to(dtype), torch.cat([-sin, sin], dim=-1).to(dtype)


def apply_rope(x: torch.Tensor, cos_full: torch.Tensor, sin_signed: torch.Tensor) -> torch.Tensor:
    """Rotate (..., S, head_dim) by :func:`rotation_tables` (S, head_dim); pairs are (i, i + head_dim / 2):
    ``[x1 cos - x2 sin, x1 sin + x2 cos] = x * [cos, cos] + [x2, x1] * [-sin, sin]``, three kernels."""
    half = x.shape[-1] // 2
    swapped = torch.cat([x[..., half:], x[..., :half]], dim=-1)
    return torch.addcmul(x * cos_full, swapped, sin_signed)
