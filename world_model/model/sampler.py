"""Sampling: Euler over the learned velocity with CFG (cameras) and APG (LiDAR), then decoding.

:class:`GuidedVelocity` is the ``velocity_fn`` of :mod:`world_model.model.flow` for a DiT under
guidance: one batched forward over [conditional; unconditional] (the unconditional half has
``Conditions.drop`` set), then classifier-free guidance on the camera views and Adaptive
Projected Guidance on the LiDAR view (§4.1), both from the same two predictions.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from world_model.model.conditions import Conditions
from world_model.model.config import SamplerConfig
from world_model.model.dit import MultiViewDiT
from world_model.model.flow import euler_sample, gaussian, predict_x0
from world_model.model.guidance import AdaptiveProjectedGuidance, cfg_combine
from world_model.model.vae import SensorVAE
from world_model.observation import ALL_SENSORS, Observation, SensorSelection
from world_model.sensors import LidarSpec

# Frames per VAE decoder call: a vector env's newest frames go in one call; long clips in bounded pieces.
DECODE_FRAMES_PER_CALL = 16


class GuidedVelocity:
    """velocity_fn(x_t (B, T, V, C, h, w), t (B,) or (B, T)) -> guided velocity, same shape as x_t."""

    def __init__(
        self,
        model: MultiViewDiT,
        cond: Conditions,
        sampler: SamplerConfig | None = None,
        **forward_kwargs: Any,
    ) -> None:
        self.model = model
        self.sampler = sampler or model.cfg.sampler
        self.kwargs = forward_kwargs
        self.lidar = model.cfg.sensors.lidar_view
        self.guided = self.sampler.camera_cfg_scale != 1.0 or self.sampler.lidar_apg_scale != 1.0
        # Conditional and unconditional rows interleaved (c0, u0, c1, u1, ...): each sample's pair
        # is one contiguous block, as in a batch of one, so the forward can be row-independent
        # (world_model.model.rows). Per-row tensors of ``forward_kwargs`` (a history's K/V) are in
        # that order too: ``pairs`` picks it from [conditional rows; unconditional rows].
        b = cond.batch_size
        self.pairs = torch.arange(2 * b, device=cond.drop.device).view(2, b).t().flatten()
        both = Conditions.cat([cond, cond.with_drop(True)]).apply(lambda _, v: v[self.pairs]) if self.guided else cond
        self.tokens = model.tokenize(both)
        s = self.sampler
        self.apg = AdaptiveProjectedGuidance(s.lidar_apg_scale, s.apg_eta, s.apg_norm_threshold, s.apg_momentum)

    def __call__(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        if not self.guided:
            return self.model(x, t, self.tokens, **self.kwargs)
        if bool((t >= 1.0).any()):
            raise ValueError("guided velocity is evaluated at t < 1 only (t = 1 is clean data)")
        v = self.model(x.repeat_interleave(2, dim=0), t.repeat_interleave(2, dim=0), self.tokens, **self.kwargs)
        v_c, v_u = v[0::2], v[1::2]
        out = cfg_combine(v_c, v_u, self.sampler.camera_cfg_scale)
        tl = t if t.ndim == 2 else t[:, None].expand(x.shape[:2])  # (B, T): x0 per frame
        xl = x[:, :, self.lidar]
        d_c, d_u = predict_x0(xl, v_c[:, :, self.lidar], tl), predict_x0(xl, v_u[:, :, self.lidar], tl)
        d_g = self.apg(d_c, d_u)
        out[:, :, self.lidar] = (d_g - xl) / (1.0 - tl)[..., None, None, None]
        return out


@torch.no_grad()
def sample_latents(
    model: MultiViewDiT,
    cond: Conditions,
    generator: torch.Generator | None = None,
    sampler: SamplerConfig | None = None,
    noise: torch.Tensor | None = None,
) -> torch.Tensor:
    """Sample latents (B, T, V, C, h, w) for ``cond`` (T frames) with ``sampler.steps`` Euler steps."""
    cfg = model.cfg
    sampler = sampler or cfg.sampler
    device = next(model.parameters()).device
    if noise is None:
        shape = (cond.batch_size, *cfg.latent_shape(cond.num_frames))
        noise = gaussian(shape, generator, device)
    was_training = model.training
    model.eval()
    try:
        return euler_sample(GuidedVelocity(model, cond.to(device), sampler), noise, sampler.steps, cfg.flow.shift)
    finally:
        model.train(was_training)


# function-size: the decoder's three optional maps as Conditions.decoder_inputs names them, and the sensors
@torch.no_grad()
def latents_to_observations(
    vae: SensorVAE,
    latents: torch.Tensor,
    lidar_spec: LidarSpec | None = None,
    bev: np.ndarray | None = None,
    frames_per_call: int = DECODE_FRAMES_PER_CALL,
    labels: torch.Tensor | np.ndarray | None = None,
    style: torch.Tensor | np.ndarray | None = None,
    nearness: torch.Tensor | np.ndarray | None = None,
    sensors: SensorSelection = ALL_SENSORS,
    range_nearness: torch.Tensor | np.ndarray | None = None,
    precipitation: torch.Tensor | np.ndarray | None = None,
    precipitation_rgb: torch.Tensor | np.ndarray | None = None,
) -> list[list[Observation]]:
    """Decode latents (B, T, V, C, h, w) to B lists of T observations (cameras uint8, LiDAR metres;
    a sensor left out of ``sensors`` is not decoded and is None in every observation).

    Frames of all samples are decoded together, ``frames_per_call`` at a time: one batched call
    for a vector env's rows, bounded memory for long clips. ``bev`` (B, T, h, w, c), when given, is
    attached to the observations unchanged. ``labels`` (B, T, Vc, 3, H, W): the frames' camera label
    maps (``Conditions.labels``), ``style`` (B, Dt): each sample's scene style (``Conditions.style``)
    and ``nearness`` (B, T, H, W): the LiDAR view's nearness maps (``Conditions.lidar_nearness``),
    read by a decoder that draws the scene; ``range_nearness`` (B, T, beams, azimuth): the same at
    the range map's resolution (``Conditions.range_nearness``), read by a VAE's range head;
    ``precipitation`` (B, T, Vc, H, W) and ``precipitation_rgb`` (B, T, 3): the rain or snow blended
    over the decoded cameras (``Conditions.precipitation``, ``Conditions.precipitation_rgb``).
    """
    b, t = latents.shape[:2]
    flat = latents.flatten(0, 1)
    if b * t == 0:
        return [[] for _ in range(b)]
    device = latents.device  # the label maps travel as uint8, once
    draw_cameras, draw_lidar = vae.draws_labels and sensors.cameras, vae.draws_labels and sensors.lidar
    flat_labels = torch.as_tensor(labels, device=device).flatten(0, 1) if draw_cameras and labels is not None else None
    flat_style = (
        torch.as_tensor(style, device=device).repeat_interleave(t, dim=0)
        if draw_cameras and style is not None
        else None
    )
    flat_near = torch.as_tensor(nearness, device=device).flatten(0, 1) if draw_lidar and nearness is not None else None
    with_head = vae.range_head is not None and sensors.lidar and range_nearness is not None
    flat_range = torch.as_tensor(range_nearness, device=device).flatten(0, 1) if with_head else None
    parts = [
        vae.decode_frames(
            flat[i : i + frames_per_call],
            lidar_spec,
            None if flat_labels is None else flat_labels[i : i + frames_per_call],
            None if flat_style is None else flat_style[i : i + frames_per_call],
            None if flat_near is None else flat_near[i : i + frames_per_call],
            sensors,
            None if flat_range is None else flat_range[i : i + frames_per_call],
        )
        for i in range(0, b * t, frames_per_call)
    ]
    cams, lidar = (None if arrays[0] is None else np.concatenate(arrays) for arrays in zip(*parts, strict=True))
    if cams is not None and precipitation is not None:
        cams = with_precipitation(cams, _numpy(precipitation), _numpy(precipitation_rgb))
    return [
        [
            Observation(
                None if cams is None else cams[i * t + j],
                None if lidar is None else lidar[i * t + j],
                None if bev is None else np.asarray(bev[i, j]),
            )
            for j in range(t)
        ]
        for i in range(b)
    ]


def _numpy(x: torch.Tensor | np.ndarray) -> np.ndarray:
    return x.cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def with_precipitation(cams: np.ndarray, alpha: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """Decoded cameras (N, Vc, H, W, 3) uint8 with each frame's rain or snow, alpha (N, Vc, H, W) and
    colour (N, 3) (any leading shape of N frames), blended over them in place as the simulator
    blends its own (:mod:`world_model.sim.precipitation`); frames without any are left as they are."""
    if alpha.size == 0:  # a model without a label decoder: no maps, no precipitation
        return cams
    from world_model.sim.precipitation import blend  # the renderer loads only where it rains or snows

    n, vc, h, w, _ = cams.shape
    alpha, rgb = alpha.reshape(n, vc * h, w), rgb.reshape(n, 3)
    for k in np.flatnonzero(alpha.reshape(n, -1).any(axis=1)):
        cams[k] = blend(cams[k].reshape(vc * h, w, 3), alpha[k], rgb[k]).reshape(vc, h, w, 3)
    return cams


def generate(
    model: MultiViewDiT,
    vae: SensorVAE,
    cond: Conditions,
    generator: torch.Generator | None = None,
    sampler: SamplerConfig | None = None,
    lidar_spec: LidarSpec | None = None,
) -> list[list[Observation]]:
    """Sample and decode: B lists of T :class:`~world_model.Observation`."""
    latents = sample_latents(model, cond, generator, sampler)
    return latents_to_observations(vae, latents, lidar_spec, **cond.decoder_inputs())
