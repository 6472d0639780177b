"""Reference-conditioned generation (paper §6): a reference latent plus an observed-region mask.

Mask semantics (one convention everywhere): ``mask`` is ``(B, T, V, 1, h, w)`` in {0, 1} on the
latent grid, views = cameras then LiDAR.

* ``mask = 1``: the region is **observed**; its latent is taken from the reference.
* ``mask = 0``: the region is **generated** from the controls; the reference is zero there.

The DiT input is ``cat([x_t, reference * mask, mask], dim=channels)``: ``C + (C + 1)`` channels, so a
reference model has ``DitConfig.in_channels_extra = C + 1`` (:func:`reference_model_config`). The
control-token pathway is unchanged. The reference spans the noise latent's full (T, V, h, w); for a
first-frame task only frame 0 carries ones.

Tasks (one model family, :class:`ReferenceConfig` holds the training probabilities):

* ``unconditional``: all-zero mask: controls only (the env's ``reset()`` without an image);
* ``first_frame_all``: every camera of frame 0 (+ the LiDAR with ``lidar_reference_prob``);
* ``first_frame_single``: one camera of frame 0;
* ``object_completion``: everything observed except one object's projected 3D box region, in
  every frame and view (:func:`object_region`).

After sampling, observed regions are pasted from the reference (``ReferenceConfig.paste_observed``)
so the generated frame agrees exactly with what the user gave.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch

from world_model.geometry import BOX_EDGES
from world_model.model.conditions import Conditions
from world_model.model.config import ModelConfig, SamplerConfig
from world_model.model.dit import MultiViewDiT
from world_model.model.flow import euler_sample, gaussian
from world_model.model.sampler import GuidedVelocity, latents_to_observations
from world_model.model.tokens import ControlTokens
from world_model.model.vae import SensorVAE, cameras_to_images, lidar_to_images
from world_model.observation import ALL_SENSORS, Observation, SensorSelection
from world_model.scene import SceneFrame
from world_model.streaming import StreamingConfig

TASKS = ("unconditional", "first_frame_all", "first_frame_single", "object_completion")


@dataclass(frozen=True)
class ReferenceConfig:
    """Training task mix and inference behaviour of the reference-conditioned model."""

    p_unconditional: float = 0.1
    p_first_frame_all: float = 0.3
    p_first_frame_single: float = 0.3
    p_object_completion: float = 0.3
    lidar_reference_prob: float = 0.5  # first_frame_all also observes the LiDAR this often
    first_frame_only_prob: float = 0.25  # batches cut to one frame: the reset() case (T = 1)
    near_plane_m: float = 0.1  # box corners closer than this to a camera are clipped (as the simulator)
    margin_px: int = 2  # object regions grow by this many view pixels: rendered edges are anti-aliased
    edge_samples: int = 16  # points per box edge when bounding the box in the LiDAR range map
    paste_observed: bool = True  # copy observed regions from the reference after sampling

    def __post_init__(self) -> None:
        p = self.task_probs
        if min(p) < 0 or not math.isclose(sum(p), 1.0, abs_tol=1e-6):
            raise ValueError(f"task probabilities must be >= 0 and sum to 1, got {p}")

    @property
    def task_probs(self) -> tuple[float, ...]:
        """Probabilities in the order of :data:`TASKS`."""
        return (self.p_unconditional, self.p_first_frame_all, self.p_first_frame_single, self.p_object_completion)


def reference_channels(cfg: ModelConfig) -> int:
    """Extra DiT input channels of a reference model: reference latent (C) + mask (1)."""
    return cfg.vae.latent_channels + 1


def reference_model_config(cfg: ModelConfig) -> ModelConfig:
    """``cfg`` with the DiT's input widened for reference conditioning."""
    return replace(cfg, dit=replace(cfg.dit, in_channels_extra=reference_channels(cfg)))


def expand_teacher(teacher: MultiViewDiT) -> MultiViewDiT:
    """A reference model initialized from ``teacher``: same weights, the new input channels of the
    patch embedding zero-initialized, so it computes exactly the teacher's velocity at start."""
    cfg = teacher.cfg
    if cfg.dit.in_channels_extra != 0:
        raise ValueError(f"expected a teacher without extra input channels, got {cfg.dit.in_channels_extra}")
    model = MultiViewDiT(reference_model_config(cfg))
    state = dict(teacher.state_dict())
    old = state["patch_in.weight"]  # (D, C * p * p): patch features are channel-major
    new = torch.zeros_like(model.patch_in.weight)
    new[:, : old.shape[1]] = old
    state["patch_in.weight"] = new
    model.load_state_dict(state)
    return model.train(teacher.training)


def teacher_from_reference(reference: MultiViewDiT) -> MultiViewDiT:
    """The inverse of :func:`expand_teacher`: ``reference`` without its reference input channels, a
    model of the teacher's config that computes exactly the reference model's velocity on an
    all-zero reference and mask (its ``unconditional`` task). A bundle carries no teacher; this
    stands in for it where a teacher scores the student's samples (the ``steps`` stage)."""
    cfg = reference.cfg
    extra = cfg.dit.in_channels_extra
    if extra != reference_channels(cfg):
        raise ValueError(f"expected a reference model with {reference_channels(cfg)} extra input channels, got {extra}")
    model = MultiViewDiT(replace(cfg, dit=replace(cfg.dit, in_channels_extra=0)))
    state = dict(reference.state_dict())
    state["patch_in.weight"] = state["patch_in.weight"][:, : model.patch_in.weight.shape[1]].clone()
    model.load_state_dict(state)
    return model.train(reference.training)


def reference_input(latents: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B, T, V, C, h, w) latents + (B, T, V, 1, h, w) mask -> (B, T, V, C + 1, h, w) extra channels."""
    if mask.shape[:3] != latents.shape[:3] or mask.shape[3] != 1 or mask.shape[4:] != latents.shape[4:]:
        raise ValueError(f"mask {tuple(mask.shape)} does not match latents {tuple(latents.shape)} (C -> 1)")
    mask = mask.to(latents.dtype)
    return torch.cat([latents * mask, mask], dim=3)


# -- masks ------------------------------------------------------------------------------------


def _cells(lo: float, hi: float, size: int, down: int) -> slice:
    """Latent cells (of ``down`` pixels) intersecting the pixel span [lo, hi), clipped to [0, size)."""
    a = max(0, math.floor(lo) // down)
    b = min(size, -(-math.ceil(hi) // down))
    return slice(a, max(a, b))


def _lidar_box_region(corners: np.ndarray, cfg: ModelConfig, samples: int, margin: int) -> np.ndarray:
    """(h, w) bool latent cells of the LiDAR view that the box's azimuth/elevation span touches.

    The range map's column k is centred on azimuth pi - 2 pi k / A and row r on elevation
    el_max - r * step; resizing to the view (H, W) keeps pixel extents, so a column span
    [k0, k1 + 1) becomes [k0 W / A, (k1 + 1) W / A) in view pixels (rows likewise).
    """
    spec, s, d = cfg.sensors.lidar, cfg.sensors, cfg.vae.downsample
    h, w = cfg.latent_hw
    t = np.linspace(0.0, 1.0, samples)[:, None]
    pts = np.concatenate([corners[a] + t * (corners[b] - corners[a]) for a, b in BOX_EDGES])
    az = np.arctan2(pts[:, 1], pts[:, 0])
    el = np.arctan2(pts[:, 2], np.hypot(pts[:, 0], pts[:, 1]))
    # Azimuth relative to the box's mean direction, so a box behind the ego does not wrap.
    centre = math.atan2(np.sin(az).mean(), np.cos(az).mean())
    rel = (az - centre + np.pi) % (2 * np.pi) - np.pi
    col = s.width / (2 * np.pi)
    u_lo = (np.pi - centre - rel.max()) * col
    u_hi = (np.pi - centre - rel.min()) * col + s.width / spec.azimuth
    el_max = math.radians(spec.elevation_max_deg)
    step = (el_max - math.radians(spec.elevation_min_deg)) / max(spec.beams - 1, 1)
    row = s.height / spec.beams
    v_lo = (el_max - el.max()) / step * row
    v_hi = ((el_max - el.min()) / step + 1.0) * row
    out = np.zeros((h, w), bool)
    u_lo, u_hi, v_lo, v_hi = u_lo - margin, u_hi + margin, v_lo - margin, v_hi + margin
    rows = _cells(v_lo, v_hi, h, d)
    if u_hi - u_lo >= s.width:
        out[rows] = True
    else:
        out[rows, np.arange(math.floor(u_lo) // d, -(-math.ceil(u_hi) // d)) % w] = True
    return out


def object_region(frame: SceneFrame, track_id: str, cfg: ModelConfig, rcfg: ReferenceConfig) -> np.ndarray:
    """(V, h, w) bool: latent cells covered by object ``track_id``'s projected 3D box in each view.

    Cameras: every latent cell intersecting the box's pixel extent (:meth:`CameraSpec.box_extent`).
    LiDAR: the cells of the range-map view spanned by the box's azimuth/elevation. Both extents
    grow by ``rcfg.margin_px`` view pixels first (0 = exactly the projected box).
    """
    ids = [o.track_id for o in frame.objects]
    if track_id not in ids:
        raise KeyError(f"object {track_id!r} is not in frame {frame.frame_index}; objects are {ids}")
    corners = frame.object_corners_lidar()[ids.index(track_id)]
    h, w = cfg.latent_hw
    d = cfg.vae.downsample
    out = np.zeros((cfg.sensors.num_views, h, w), bool)
    for v in range(cfg.sensors.num_cameras):
        box = frame.rig.cameras[v].box_extent(corners, rcfg.near_plane_m)
        if box is not None:
            x0, y0, x1, y1 = box
            m = rcfg.margin_px
            out[v, _cells(y0 - m, y1 + m, h, d), _cells(x0 - m, x1 + m, w, d)] = True
    out[cfg.sensors.lidar_view] = _lidar_box_region(corners, cfg, rcfg.edge_samples, rcfg.margin_px)
    return out


def category_region(
    frames: Sequence[SceneFrame], category: str | None, cfg: ModelConfig, rcfg: ReferenceConfig
) -> np.ndarray:
    """(T, V, h, w) bool: per frame, the union of :func:`object_region` over the objects of
    ``category`` (None: over every object)."""
    out = np.zeros((len(frames), cfg.sensors.num_views, *cfg.latent_hw), bool)
    for f, fr in enumerate(frames):
        for o in fr.objects:
            if category is None or o.category == category:
                out[f] |= object_region(fr, o.track_id, cfg, rcfg)
    return out


def task_mask(
    task: str,
    cfg: ModelConfig,
    frames: Sequence[SceneFrame],
    rng: np.random.Generator,
    rcfg: ReferenceConfig,
) -> np.ndarray:
    """(T, V, 1, h, w) float32 mask (1 = observed) of one training example for ``task``.

    Random choices (the single view, the LiDAR, the completed object) come from ``rng``.
    ``object_completion`` without an object in view falls back to ``first_frame_all``.
    """
    t, v, (h, w) = len(frames), cfg.sensors.num_views, cfg.latent_hw
    mask = np.zeros((t, v, 1, h, w), np.float32)
    if task == "unconditional":
        return mask
    if task == "first_frame_single":
        mask[0, int(rng.integers(cfg.sensors.num_cameras))] = 1.0
        return mask
    if task == "object_completion":
        ids = [o.track_id for o in frames[0].objects]
        if ids:
            track = ids[int(rng.integers(len(ids)))]
            mask[:] = 1.0
            for f, fr in enumerate(frames):
                if any(o.track_id == track for o in fr.objects):
                    mask[f, :, 0][object_region(fr, track, cfg, rcfg)] = 0.0
            if mask.min() == 0.0:
                return mask
        task = "first_frame_all"
    if task == "first_frame_all":
        mask[0, : cfg.sensors.num_cameras] = 1.0
        if rng.random() < rcfg.lidar_reference_prob:
            mask[0, cfg.sensors.lidar_view] = 1.0
        return mask
    raise ValueError(f"unknown task {task!r}; choose one of {TASKS}")


# -- inference --------------------------------------------------------------------------------


# How a one-step first-frame model (the ``first_frame`` stage's, distilled from a reference model's
# guided sampler) samples: one Euler step from pure noise, its x0-prediction, unguided.
ONE_STEP = SamplerConfig(steps=1, camera_cfg_scale=1.0, lidar_apg_scale=1.0)


def first_frame_sampling(
    reference: ReferenceGenerator, one_step: ReferenceGenerator | None, streaming: StreamingConfig
) -> tuple[ReferenceGenerator, dict[str, Any]]:
    """Who draws a first frame from controls, and the keywords of its ``sample``: the one-step
    first-frame model in one unguided step (:data:`ONE_STEP`) where there is one and ``streaming``
    asks for it, else the reference model at ``streaming``'s first-frame settings."""
    if one_step is not None and streaming.one_step_first_frame:
        return one_step, {"sampler": ONE_STEP}
    return reference, {"steps": streaming.first_frame_steps, "guidance": streaming.first_frame_guidance}


class _WithReference:
    """Presents a reference model to :class:`GuidedVelocity` as a plain DiT: the reference
    channels are appended to x (and repeated for the unconditional half of guidance; the
    reference is an observation, not a control, so guidance never drops it)."""

    def __init__(self, model: MultiViewDiT, extra: torch.Tensor) -> None:
        self.model, self.extra, self.cfg = model, extra, model.cfg

    def tokenize(self, cond: Conditions) -> ControlTokens:
        return self.model.tokenize(cond)

    def __call__(self, x: torch.Tensor, t: torch.Tensor, tokens: ControlTokens, **kw: Any) -> torch.Tensor:
        extra = self.extra.repeat_interleave(x.shape[0] // self.extra.shape[0], dim=0)  # guidance's (c, u) pairs
        return self.model(torch.cat([x, extra.to(x.dtype)], dim=3), t, tokens, **kw)


class ReferenceGenerator:
    """First frames from controls / one view / all views, and object completion (module docstring).

    ``model`` is a reference model (``in_channels_extra = C + 1``, from ``--stage reference``); a
    plain teacher is accepted for the controls-only path (``reference=None``).
    """

    def __init__(self, model: MultiViewDiT, vae: SensorVAE, cfg: ReferenceConfig | None = None) -> None:
        mc, vc = model.cfg, vae.cfg
        if mc.vae.model_settings() != vc.vae.model_settings() or mc.sensors != vc.sensors:
            raise ValueError(f"model (preset {mc.name!r}) and VAE (preset {vc.name!r}) disagree on sensors/latents")
        extra = mc.dit.in_channels_extra
        if extra not in (0, reference_channels(mc)):
            raise ValueError(f"model has {extra} extra input channels; a reference model has {reference_channels(mc)}")
        self.model, self.vae, self.cfg = model, vae, cfg or ReferenceConfig()
        self.mcfg = mc
        self.names = mc.sensors.rig().names

    @property
    def conditioned(self) -> bool:
        """True when the model takes reference channels."""
        return self.mcfg.dit.in_channels_extra > 0

    # -- references from user images --
    def _images(self, key: str, arr: np.ndarray, want: tuple[int, ...], batch: int) -> np.ndarray:
        arr = np.asarray(arr)
        if arr.shape == want:
            arr = np.broadcast_to(arr, (batch, *want))
        if arr.shape != (batch, *want):
            h, w = self.mcfg.sensors.height, self.mcfg.sensors.width
            hint = (
                f"resize camera images to the model's view size {w}x{h} (e.g. cv2.resize(img, ({w}, {h})))"
                if key == "lidar" or (h, w) not in (arr.shape[-3:-1], arr.shape[-2:])
                else "the size is right: give uint8 RGB images with channels last, (H, W, 3)"
            )
            raise ValueError(
                f"reference {key!r} must be {want} or {(batch, *want)} for this model, got {arr.shape}; {hint}"
            )
        return arr

    def encode_reference(self, reference: Mapping[str, np.ndarray] | None, batch: int) -> torch.Tensor:
        """User images -> (B, 1, V, C + 1, h, w) reference channels for the first frame.

        Keys: ``"cameras"`` uint8 (V, H, W, 3), a camera name (e.g. ``"FRONT"``) uint8 (H, W, 3),
        ``"lidar"`` metres (beams, azimuth); each optionally with a leading batch dim B.
        """
        s = self.mcfg.sensors
        v, (h, w) = s.num_views, self.mcfg.latent_hw
        device = next(self.vae.parameters()).device
        lat = torch.zeros(batch, 1, v, self.mcfg.vae.latent_channels, h, w, device=device)
        mask = torch.zeros(batch, 1, v, 1, h, w, device=device)
        valid = ("cameras", "lidar", *self.names)
        if reference is not None and not isinstance(reference, Mapping):
            raise TypeError(
                f"the reference must be a dict such as {{'FRONT': image}} or {{'cameras': images}}, "
                f"got {type(reference).__name__}"
            )
        for key, value in (reference or {}).items():
            if key not in valid:
                raise ValueError(f"unknown reference key {key!r}; use one of {valid}")
            if key == "lidar":
                ranges = self._images(key, value, (s.lidar.beams, s.lidar.azimuth), batch)
                if ranges.dtype.kind not in "iuf" or not np.isfinite(ranges).all():
                    raise ValueError(f"reference 'lidar' must be finite ranges in metres, got dtype {ranges.dtype}")
                if ranges.min() < 0 or ranges.max() > s.lidar.max_range:
                    raise ValueError(
                        f"reference 'lidar' ranges must lie in [0, {s.lidar.max_range:g}] m (0 = no return), "
                        f"got [{ranges.min():g}, {ranges.max():g}]"
                    )
                images = lidar_to_images(ranges.astype(np.float32), self.mcfg, device)[:, None]
                views = [s.lidar_view]
            else:
                many = key == "cameras"
                want = (s.num_cameras, s.height, s.width, 3) if many else (s.height, s.width, 3)
                cams = self._images(key, value, want, batch)
                if cams.dtype != np.uint8:
                    raise ValueError(f"reference {key!r} must be uint8 RGB, got {cams.dtype}")
                images = cameras_to_images(cams if many else cams[:, None], device)
                views = list(range(s.num_cameras)) if many else [self.names.index(key)]
            with torch.no_grad():
                enc = self.vae.encode(images.flatten(0, 1))
            lat[:, 0, views] = enc.view(batch, len(views), *enc.shape[1:])
            mask[:, 0, views] = 1.0
        return reference_input(lat, mask)

    # -- sampling --
    @torch.no_grad()
    def sample(
        self,
        cond: Conditions,
        extra: torch.Tensor | None = None,
        steps: int | None = None,
        seed: int | Sequence[int] = 0,
        sampler: SamplerConfig | None = None,
        guidance: float | None = None,
    ) -> torch.Tensor:
        """Latents (B, T, V, C, h, w) for ``cond`` anchored on ``extra`` (B, T, V, C + 1, h, w)
        reference channels (:func:`reference_input`); None = controls only. ``seed``: of the
        batch's noise, or one per row (row i's noise then as in a batch of one seeded ``seed[i]``).
        ``steps`` and ``guidance`` (the cameras' classifier-free guidance scale) replace those of
        ``sampler`` (default: the model config's)."""
        mc = self.mcfg
        sampler = replace(
            sampler or mc.sampler,
            **({"steps": steps} if steps else {}),
            **({"camera_cfg_scale": guidance} if guidance is not None else {}),
        )
        shape = (cond.batch_size, *mc.latent_shape(cond.num_frames))
        if extra is not None and tuple(extra.shape) != (*shape[:3], reference_channels(mc), *shape[4:]):
            raise ValueError(f"reference channels must be {(*shape[:3], reference_channels(mc), *shape[4:])}")
        observed = extra is not None and bool(extra[:, :, :, -1].any())
        if observed and not self.conditioned:
            raise ValueError("this model has no reference channels; train one with --stage reference")
        device = next(self.model.parameters()).device
        if isinstance(seed, int):
            noise = gaussian(shape, torch.Generator().manual_seed(seed), device)
        elif len(seed) == shape[0]:  # one seed per row: each row's noise as in a batch of one
            rows = [gaussian((1, *shape[1:]), torch.Generator().manual_seed(s), device) for s in seed]
            noise = torch.cat(rows)
        else:
            raise ValueError(f"seed: one int or one per row ({shape[0]}), got {len(seed)}")
        net = self.model
        if self.conditioned:
            if extra is None:
                extra = torch.zeros(*shape[:3], reference_channels(mc), *shape[4:], device=device)
            net = _WithReference(self.model, extra.to(device))
        was_training = self.model.training
        self.model.eval()
        try:
            x = euler_sample(GuidedVelocity(net, cond.to(device), sampler), noise, sampler.steps, mc.flow.shift)
        finally:
            self.model.train(was_training)
        if observed and self.cfg.paste_observed:
            c = mc.vae.latent_channels
            m = extra[:, :, :, c:].to(device)
            x = m * extra[:, :, :, :c].to(device) + (1.0 - m) * x
        return x

    def first_frame(
        self,
        cond: Conditions,
        reference: Mapping[str, np.ndarray] | None = None,
        steps: int | None = None,
        seed: int = 0,
        sensors: SensorSelection = ALL_SENSORS,
        guidance: float | None = None,
    ) -> tuple[torch.Tensor, list[Observation]]:
        """The first multi-view frame (+ LiDAR) from controls (``reference=None``), one view
        (``{"FRONT": (H, W, 3)}``) or all views (``{"cameras": (V, H, W, 3)}``); ``steps`` and
        ``guidance`` as in :meth:`sample`.

        Returns normalized latents (B, 1, V, C, h, w), ready to seed the causal student's cache,
        and B observations, of the ``sensors`` decoded. Only the first frame of ``cond`` is used.
        """
        cond = cond.frames(0, 1)
        lat = self.first_latents(cond, reference, steps, seed, guidance)
        obs = latents_to_observations(self.vae, lat, self.mcfg.sensors.lidar, **cond.decoder_inputs(), sensors=sensors)
        return lat, [o[0] for o in obs]

    def first_latents(
        self,
        cond: Conditions,
        reference: Mapping[str, np.ndarray] | None = None,
        steps: int | None = None,
        seed: int = 0,
        guidance: float | None = None,
    ) -> torch.Tensor:
        """:meth:`first_frame`'s latents (B, 1, V, C, h, w), not decoded."""
        cond = cond.frames(0, 1)
        extra = self.encode_reference(reference, cond.batch_size) if reference else None
        return self.sample(cond, extra, steps, seed, guidance=guidance)

    def from_first_frame(
        self, cond: Conditions, reference: Mapping[str, np.ndarray], steps: int | None = None, seed: int = 0
    ) -> tuple[torch.Tensor, list[list[Observation]]]:
        """Tasks (a)/(b): all ``cond.num_frames`` frames anchored on a first-frame reference."""
        first = self.encode_reference(reference, cond.batch_size)
        extra = first.new_zeros(first.shape[0], cond.num_frames, *first.shape[2:])
        extra[:, :1] = first
        lat = self.sample(cond, extra, steps, seed)
        return lat, latents_to_observations(self.vae, lat, self.mcfg.sensors.lidar, **cond.decoder_inputs())

    def complete_category(
        self,
        cond: Conditions,
        latents: torch.Tensor,
        frames: Sequence[SceneFrame],
        category: str,
        steps: int | None = None,
        seed: int = 0,
        guidance: float | None = None,
    ) -> torch.Tensor:
        """Task (c) on first frames already generated: regenerate the projected boxes of every
        ``category`` object in ``latents`` (B, 1, V, C, h, w), one SceneFrame per row, the rest of
        each frame observed. A row without the category comes back unchanged (all of it observed,
        and observed cells are pasted back); so does the batch when no row holds it. ``steps`` and
        ``guidance`` as in :meth:`sample`."""
        if latents.shape[1] != 1 or len(frames) != latents.shape[0]:
            raise ValueError(
                f"need one frame per row of single-frame latents, got {len(frames)} for {tuple(latents.shape)}"
            )
        region = np.stack([category_region([fr], category, self.mcfg, self.cfg)[0] for fr in frames])  # (B, V, h, w)
        if not region.any():
            return latents
        mask = torch.as_tensor(~region, dtype=latents.dtype, device=latents.device)[:, None, :, None]
        return self.sample(cond.frames(0, 1), reference_input(latents, mask), steps, seed, guidance=guidance)

    def complete_object(
        self,
        cond: Conditions,
        frames: Sequence[SceneFrame],
        cameras: np.ndarray,
        lidar: np.ndarray,
        track_id: str,
        steps: int | None = None,
        seed: int = 0,
    ) -> tuple[torch.Tensor, list[list[Observation]], np.ndarray]:
        """Task (c): regenerate object ``track_id`` in a clip (T frames) under its controls.

        ``cameras`` uint8 (T, V, H, W, 3) and ``lidar`` metres (T, beams, azimuth) are the observed
        clip; the object's projected box is masked out and generated. Batch size 1. Returns latents
        (1, T, V, C, h, w), the decoded observations and the (T, V, 1, h, w) mask used.
        """
        if cond.batch_size != 1 or cond.num_frames != len(frames):
            raise ValueError(
                f"complete_object needs one sequence of {len(frames)} frames, got cond "
                f"{cond.batch_size} x {cond.num_frames}"
            )
        mask = np.ones((len(frames), self.mcfg.sensors.num_views, 1, *self.mcfg.latent_hw), np.float32)
        for f, fr in enumerate(frames):
            if any(o.track_id == track_id for o in fr.objects):
                mask[f, :, 0][object_region(fr, track_id, self.mcfg, self.cfg)] = 0.0
        lat = self.vae.encode_frames(np.asarray(cameras), np.asarray(lidar, dtype=np.float32))
        extra = reference_input(lat[None], torch.as_tensor(mask, device=lat.device)[None])
        out = self.sample(cond, extra, steps, seed)
        return (
            out,
            latents_to_observations(self.vae, out, self.mcfg.sensors.lidar, **cond.decoder_inputs()),
            mask,
        )
