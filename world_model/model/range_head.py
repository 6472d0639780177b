"""The LiDAR at the range map's own resolution: the decoder's LiDAR view finished by the scene.

The VAE sees the range map (beams x azimuth, 32 x 1024) squeezed to the camera views' size
(64 x 112), so a car 25 m ahead, about 11 azimuth columns wide, is one column of the LiDAR view
and less than a latent cell: decoded and stretched back, it is a faint smear, farther than the car.
The decoder's nearness gate draws the scene's ranges at the view's resolution and cannot give the
edge back. :class:`RangeHead` works at the range map's resolution instead: it reads the decoder's
LiDAR view stretched back (bilinear, as :func:`~world_model.model.vae.images_to_lidar` reads it)
and the range map the scene implies there, one ray per beam and column
(:func:`~world_model.raster.maps.range_nearness_maps`, in finer steps than the view's), and moves
each cell toward the scene's range by a learned share::

    up     = bilinear(view -> beams x azimuth)              the decoder's LiDAR, in [-1, 1]
    target = 1 - 2 * nearness / RANGE_LEVELS                 the scene's range; +1 (no return) where
                                                             nothing is in range
    share  = clamp(net([up, target, nearness > 0]), 0, 1)    3 convolutions at full resolution
    out    = up + share * (target - up)

The share is zero-initialized: an untrained head is the stretched view, the LiDAR as decoded
without it. Its stage (:mod:`world_model.train.range_head_stage`) trains it alone on the student's
own rollouts, every other weight frozen, with :func:`range_loss`: where the scene and the
recording agree (the procedural world's LiDAR is such a ray cast) it learns to stand the returns
where the scene puts them; on a recording with returns the scene does not model, the share stays
where the latents know better.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping

import torch
import torch.nn.functional as F
from torch import nn

from world_model.model.layout import RANGE_LEVELS

# Features of the head's convolutions: three 3x3 layers see 7 x 7 cells (7 beams, 2.5 degrees of
# azimuth), the edge of a car and the ground around it; ~0.2 GFLOP a range map.
RANGE_HEAD_WIDTH = 16


class RangeHead(nn.Module):
    """(N, 1, H, W) LiDAR view + (N, beams, azimuth) uint16 nearness -> (N, 1, beams, azimuth) in [-1, 1]."""

    def __init__(self, width: int = RANGE_HEAD_WIDTH) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(3, width, 3, padding=1),
            nn.SiLU(),
            nn.Conv2d(width, width, 3, padding=1),
            nn.SiLU(),
            nn.Conv2d(width, 1, 3, padding=1),
        )
        # The share starts at 0 (the stretched view); torch.clamp passes the gradient at 0.
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def forward(self, view: torch.Tensor, nearness: torch.Tensor) -> torch.Tensor:
        """``view`` (N, 1, H, W): the decoder's LiDAR view in [-1, 1] (its three channels
        averaged); ``nearness`` (N, beams, azimuth) uint16, the scene's at the range map's resolution
        (:data:`~world_model.model.layout.RANGE_LEVELS` steps)."""
        if nearness.ndim != 3 or len(nearness) != len(view):
            raise ValueError(f"nearness must be (N={len(view)}, beams, azimuth) maps, got {tuple(nearness.shape)}")
        up = F.interpolate(view.float(), size=tuple(nearness.shape[-2:]), mode="bilinear", align_corners=False)
        near = nearness.to(device=up.device, dtype=up.dtype)[:, None] / RANGE_LEVELS
        target = 1.0 - 2.0 * near
        # Channels-last: oneDNN's convolutions at this width run about twice as fast on a CPU.
        features = torch.cat([up, target, (near > 0).to(up.dtype)], dim=1).contiguous(memory_format=torch.channels_last)
        share = torch.clamp(self.net(features), 0.0, 1.0)
        return up + share * (target - up)


def finished_digest(vae_state: Mapping[str, torch.Tensor]) -> str:
    """What a range head was trained to finish: a digest of a VAE's weights but the head's own
    (``range_head.*``) and the cameras' decoder's (``camera_decoder.*``, which draws no LiDAR). A
    head trained on one decoder does not finish another."""
    h = hashlib.sha256()
    for key in sorted(k for k in vae_state if not k.startswith(("range_head.", "camera_decoder."))):
        h.update(key.encode())
        h.update(vae_state[key].detach().cpu().float().contiguous().numpy().tobytes())
    return "vae-" + h.hexdigest()[:16]


def range_loss(
    prediction: torch.Tensor, target: torch.Tensor, objects: torch.Tensor, object_weight: float
) -> torch.Tensor:
    """Mean absolute error of range maps in image values, (N, 1, beams, azimuth) each, with every
    cell of ``objects`` (same shape, bool: the recording's returns off the road) weighing
    ``object_weight`` times a road's or the sky's: objects are a few percent of the cells and
    all a policy reacts to."""
    if prediction.shape != target.shape or objects.shape != target.shape:
        raise ValueError(f"shapes differ: {tuple(prediction.shape)}, {tuple(target.shape)}, {tuple(objects.shape)}")
    weights = 1.0 + (object_weight - 1.0) * objects.to(prediction.dtype)
    return ((prediction - target).abs() * weights).sum() / weights.sum()
