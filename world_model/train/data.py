"""Training data: random sensor frames for the VAE, cached latent windows + conditions for the DiT."""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, fields, replace
from pathlib import Path
from typing import NamedTuple, TypeVar

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from world_model.data import Clip, iter_clips
from world_model.data.clips import clip_fingerprint
from world_model.geometry import wrap_angle
from world_model.model.conditions import (
    ConditionArrays,
    ConditionOptions,
    Conditions,
    as_held,
    build_condition_arrays,
)
from world_model.model.config import ModelConfig, without_label_decoder
from world_model.model.imagedesc import ImageDescriptionEncoder
from world_model.model.layout import NEARNESS_LEVELS, layout_sequence
from world_model.model.reference import ReferenceConfig
from world_model.model.text import TextEncoder
from world_model.model.vae import SensorVAE, cameras_to_images, lidar_to_images
from world_model.raster.classes import LABEL_CLASSES, PAINT_BITS, SURFACE_STEPS
from world_model.raster.maps import camera_labels, lidar_nearness_maps
from world_model.scene import SceneFrame

NEAR_PLANE_M = ReferenceConfig().near_plane_m  # boxes clipped as the simulator and the reference masks do
# Fewer frames than this are rastered in-process (layouts, label maps): starting spawned workers
# costs about 2 s, a raster a few ms a frame.
LAYOUT_POOL_MIN_FRAMES = 2000
T = TypeVar("T")


# The last dataset (and run latents) this process opened, by key: the recipe trains every stage in
# one process on one dataset, and reading a full dataset's clips (every frame parsed) and building
# its latent windows take tens of seconds that each stage would otherwise spend again.
_last_opened: dict[str, tuple[object, object]] = {}


def dataset_stamp(data_dir: str | Path) -> tuple[str, int, int] | None:
    """What changes when a dataset gains or loses clips: its index file's path, time and size;
    None for a folder without one."""
    index = Path(data_dir) / "dataset.json"
    try:
        st = index.stat()
    except FileNotFoundError:
        return None
    return str(index.resolve()), st.st_mtime_ns, st.st_size


def remember_last(kind: str, key: object, make: Callable[[], T]) -> T:
    """``make()``, or the value it gave for the same ``key`` when that was the last ``kind`` this
    process made (None: never remembered). One value per kind is kept: the previous is dropped first."""
    last = _last_opened.pop(kind, None)
    if key is not None and last is not None and last[0] == key:
        _last_opened[kind] = last
        return last[1]  # type: ignore[return-value]
    del last
    value = make()
    if key is not None:
        _last_opened[kind] = (key, value)
    return value


def load_clips(data_dir: str | Path, cfg: ModelConfig) -> list[Clip]:
    """All clips of a dataset, checked against the model's sensors; the same list as the last call
    of this process for an unchanged dataset (:func:`remember_last`)."""
    stamp = dataset_stamp(data_dir)
    key = None if stamp is None else (stamp, cfg.sensors)
    return remember_last("clips", key, lambda: _read_clips(data_dir, cfg))


def _read_clips(data_dir: str | Path, cfg: ModelConfig) -> list[Clip]:
    clips = list(iter_clips(data_dir))
    if not clips:
        raise FileNotFoundError(f"{data_dir} has no complete clips; record some first (m4world record)")
    s = cfg.sensors
    for c in clips:
        t, v, h, w, _ = c.cameras.shape
        if (v, h, w) != (s.num_cameras, s.height, s.width):
            raise ValueError(
                f"clip {c.name}: cameras are {v} x {h}x{w} but preset {cfg.name!r} expects "
                f"{s.num_cameras} x {s.height}x{s.width}; record at the preset's resolution"
            )
        if c.bev.shape[1:] != s.bev.shape:
            raise ValueError(f"clip {c.name}: bev {c.bev.shape[1:]} but the config expects {s.bev.shape}")
    return clips


class FrameBatch(NamedTuple):
    """A VAE training batch: images (B, 3, H, W) in [-1, 1], is_lidar (B,) bool and per-pixel
    loss weights (B, 1, H, W): 1, plus ``VaeConfig.object_loss_weight`` inside objects' boxes."""

    images: torch.Tensor
    is_lidar: torch.Tensor
    weights: torch.Tensor


def object_boxes(frame: SceneFrame, view: int) -> list[tuple[int, int, int, int]]:
    """Pixel boxes (x0, y0, x1, y1) of camera ``view`` covering each object's projected 3-D box."""
    if not frame.objects:
        return []
    corners = frame.object_corners_lidar()
    boxes = (frame.rig.cameras[view].box_extent(corners[o], NEAR_PLANE_M) for o in range(len(frame.objects)))
    return [tuple(box) for box in boxes if box is not None]


def object_pixel_weights(
    frame: SceneFrame,
    view: int,
    height: int,
    width: int,
    extra: float,
    boxes: list[tuple[int, int, int, int]] | None = None,
) -> np.ndarray:
    """(H, W) float32 loss weights of camera ``view``: 1 everywhere, ``1 + extra`` inside the
    projected 3-D box of every object in view (where small objects live, which plain L1 ignores).
    ``boxes``: the view's :func:`object_boxes` when already known."""
    out = np.ones((height, width), np.float32)
    if extra == 0.0:
        return out
    for x0, y0, x1, y1 in object_boxes(frame, view) if boxes is None else boxes:
        out[y0:y1, x0:x1] = 1.0 + extra
    return out


class FrameSampler:
    """Random (clip, frame, view) images for the VAE; view == num_cameras is the LiDAR map."""

    def __init__(self, clips: list[Clip], cfg: ModelConfig) -> None:
        self.clips, self.cfg = clips, cfg
        # (clip, frame, view) -> object boxes: projecting every object is the costly part of a batch,
        # and a few hundred steps revisit the same frames many times
        self._boxes: dict[tuple[int, int, int], list[tuple[int, int, int, int]]] = {}

    def image(self, clip: int, frame: int, view: int) -> torch.Tensor:
        c = self.clips[clip]
        if view == self.cfg.sensors.lidar_view:
            return lidar_to_images(np.asarray(c.lidar[frame], dtype=np.float32), self.cfg)
        return cameras_to_images(np.asarray(c.cameras[frame, view]))

    def weights(self, clip: int, frame: int, view: int) -> torch.Tensor:
        """(1, H, W) loss weights of one image; the LiDAR map has no camera boxes: all ones."""
        s = self.cfg.sensors
        extra = 0.0 if view == s.lidar_view else self.cfg.vae.object_loss_weight
        fr = self.clips[clip].frames[frame]
        key = (clip, frame, view)
        if extra and key not in self._boxes:
            self._boxes[key] = object_boxes(fr, view)
        return torch.from_numpy(object_pixel_weights(fr, view, s.height, s.width, extra, self._boxes.get(key)))[None]

    def pick(self, rng: np.random.Generator, batch: int, views: int | None = None) -> list[tuple[int, int, int]]:
        """``batch`` random (clip, frame, view) triples of the first ``views`` views (None: all of
        them; the view may then be the LiDAR map, the last)."""
        ci = rng.integers(len(self.clips), size=batch)
        fi = [int(rng.integers(self.clips[c].num_frames)) for c in ci]
        vi = rng.integers(self.cfg.sensors.num_views if views is None else views, size=batch)
        return list(zip(ci.tolist(), fi, vi.tolist(), strict=True))

    def batch(self, picks: Sequence[tuple[int, int, int]]) -> FrameBatch:
        """The images, LiDAR flags and loss weights of (clip, frame, view) triples."""
        return FrameBatch(
            torch.stack([self.image(*p) for p in picks]),
            torch.as_tensor([v == self.cfg.sensors.lidar_view for _, _, v in picks]),
            torch.stack([self.weights(*p) for p in picks]),
        )

    def sample(self, rng: np.random.Generator, batch: int) -> FrameBatch:
        """``batch`` random images of random clips, frames and views (cameras or the LiDAR map)."""
        return self.batch(self.pick(rng, batch))

    def eval_frames(self, count: int) -> list[tuple[int, int]]:
        """Up to ``count`` (clip, frame) pairs spread over the dataset (deterministic)."""
        pairs = [(ci, f) for ci, c in enumerate(self.clips) for f in range(c.num_frames)]
        idx = np.linspace(0, len(pairs) - 1, num=min(count, len(pairs))).round().astype(int)
        return [pairs[i] for i in sorted(set(idx.tolist()))]


def file_digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def encoder_digest(vae: SensorVAE) -> str:
    """What a clip's latents depend on: the encoder's weights and the latent normalization, not
    the decoders nor the range head (the decoder stages change them alone) nor the file they were
    stored in (a bundle keeps the run's VAE)."""
    h = hashlib.sha256()
    state = vae.state_dict()
    for key in sorted(k for k in state if not k.startswith(("decoder.", "camera_decoder.", "range_head."))):
        h.update(key.encode())
        h.update(state[key].detach().cpu().float().contiguous().numpy().tobytes())
    return "encoder-" + h.hexdigest()[:16]


def latent_cache_dir(run_dir: str | Path) -> Path:
    """The run's one latent cache, shared by every stage that encodes clips (teacher, student
    stages, reference, LoRA): entries are keyed by clip name, clip fingerprint and
    :func:`encoder_digest`."""
    return Path(run_dir) / "teacher" / "latents"


def cached_latents(clip: Clip, vae: SensorVAE, cache_dir: Path, vae_digest: str) -> torch.Tensor:
    """Latents (T, V, C, h, w) of a clip, encoded once per VAE version and stored on disk.

    An entry is reused when its VAE digest and clip fingerprint match; entries written before
    fingerprints existed (digest only) get the fingerprint added on first use."""
    path = cache_dir / f"{clip.name}.safetensors"
    key = clip_fingerprint(clip)
    if path.exists():
        try:
            from safetensors import safe_open

            with safe_open(str(path), "pt") as f:
                meta = f.metadata() or {}
            if meta.get("vae") == vae_digest and meta.get("clip", key) == key:
                lat = load_file(str(path))["latents"]
                if "clip" not in meta:
                    _write_latents(path, lat, vae_digest, key)
                return lat
        except Exception:  # noqa: BLE001 - a corrupt cache entry is re-encoded
            pass
    lat = vae.encode_frames(np.asarray(clip.cameras), np.asarray(clip.lidar, dtype=np.float32)).cpu()
    _write_latents(path, lat, vae_digest, key)
    return lat


def layout_cache_dir(run_dir: str | Path) -> Path:
    """The run's cache of the clips' layout rasters, beside the latent cache."""
    return Path(run_dir) / "teacher" / "layouts"


def layout_key(cfg: ModelConfig) -> str:
    """What decides a clip's layout raster besides the clip: the layout settings, the LiDAR and the
    latent resolution."""
    # The raster is the DiT's: the decoder's switch does not change it.
    dit_layout = {k: v for k, v in asdict(cfg.layout).items() if k != "decoder"}
    blob = json.dumps([dit_layout, asdict(cfg.sensors.lidar), list(cfg.latent_hw)], sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _clip_layout(frames: list[SceneFrame], bev: np.ndarray, cfg: ModelConfig) -> np.ndarray:
    return layout_sequence(frames, bev, cfg.sensors.lidar, cfg.latent_hw, cfg.layout.supersample)


def cached_layouts(clips: list[Clip], cfg: ModelConfig, cache_dir: Path, workers: int | None = None) -> list | None:
    """Each clip's layout raster (T, V, Cl, h, w) float32, computed once per run and stored in
    ``cache_dir``; None when the config has no layout. The raster ray-casts every view of every
    frame (a few ms a frame): a dataset's worth is computed by ``workers`` processes (default: every
    core) and every later stage reads it back. The result is the same for any ``workers``."""
    if not cfg.layout.enabled:
        return None
    jobs = [(c.frames, np.asarray(c.bev), cfg) for c in clips]
    return _cached_per_clip(clips, cache_dir, "layout", layout_key(cfg), _clip_layout, jobs, workers)


def label_cache_dir(run_dir: str | Path) -> Path:
    """The run's cache of the clips' camera label maps (the decoder stages'), beside the latent cache."""
    return Path(run_dir) / "teacher" / "labels"


def cached_label_maps(
    clips: list[Clip], cfg: ModelConfig, cache_dir: Path, workers: int | None = None
) -> list[np.ndarray]:
    """Each clip's camera label maps (T, num_cameras, 3, H, W) uint8, class ids
    (:data:`~world_model.raster.classes.LABEL_CLASSES`), paint and surface (:func:`camera_labels`),
    computed once per run as :func:`cached_layouts` computes layouts: the decoder stages read them
    instead of rastering every sample of every batch."""
    s = cfg.sensors
    key = (
        f"{s.height}x{s.width}x{s.num_cameras}:{','.join(LABEL_CLASSES)}"
        f":albedo-paint{''.join(map(str, PAINT_BITS))}:surface{SURFACE_STEPS}"
    )
    jobs = [(c.frames, cfg) for c in clips]
    return _cached_per_clip(clips, cache_dir, "labels", key, camera_labels, jobs, workers)


def nearness_cache_dir(run_dir: str | Path) -> Path:
    """The run's cache of the clips' LiDAR nearness maps (the decoder stages'), beside the label maps."""
    return Path(run_dir) / "teacher" / "nearness"


def cached_nearness_maps(
    clips: list[Clip], cfg: ModelConfig, cache_dir: Path, workers: int | None = None
) -> list[np.ndarray] | None:
    """Each clip's LiDAR nearness maps (T, H, W) uint8 (:func:`lidar_nearness_maps`), computed once
    per run as :func:`cached_label_maps`; None for a decoder that does not draw the scene
    (``layout.decoder``)."""
    if not cfg.layout.decoder:
        return None
    s = cfg.sensors
    key = f"{s.height}x{s.width}:nearness{NEARNESS_LEVELS}:{json.dumps(asdict(s.lidar), sort_keys=True)}"
    jobs = [(c.frames, cfg) for c in clips]
    return _cached_per_clip(clips, cache_dir, "nearness", key, lidar_nearness_maps, jobs, workers)


def _cached_per_clip(
    clips: list[Clip],
    cache_dir: Path,
    name: str,
    key: str,
    compute: Callable[..., np.ndarray],
    jobs: list[tuple],
    workers: int | None,
) -> list[np.ndarray]:
    """``compute(*jobs[i])`` for each clip i, stored in ``cache_dir`` under the clip's name with
    ``key`` and the clip's fingerprint: read back where both match, else computed (by ``workers``
    spawned processes, default every core, for enough frames) and written."""
    out: list[np.ndarray | None] = [None] * len(clips)
    missing = []
    for i, clip in enumerate(clips):
        out[i] = _read_cached(cache_dir / f"{clip.name}.safetensors", {name: key, "clip": clip_fingerprint(clip)}, name)
        if out[i] is None:
            missing.append(i)
    workers = min(workers or os.cpu_count() or 1, len(missing))
    if workers > 1 and sum(clips[i].num_frames for i in missing) >= LAYOUT_POOL_MIN_FRAMES:
        ctx = multiprocessing.get_context("spawn")  # no fork of a process that runs torch threads
        with ProcessPoolExecutor(workers, mp_context=ctx) as pool:
            computed = [job.result() for job in [pool.submit(compute, *jobs[i]) for i in missing]]
    else:
        computed = [compute(*jobs[i]) for i in missing]
    for i, value in zip(missing, computed, strict=True):
        meta = {name: key, "clip": clip_fingerprint(clips[i])}
        _write_tensor(cache_dir / f"{clips[i].name}.safetensors", name, torch.from_numpy(value), meta)
        out[i] = value
    return out  # type: ignore[return-value]


def _read_cached(path: Path, meta: dict[str, str], name: str) -> np.ndarray | None:
    """The array ``name`` of cache entry ``path`` when its metadata holds ``meta``; None when it is
    missing, stale or corrupt (then it is recomputed)."""
    if not path.exists():
        return None
    try:
        from safetensors import safe_open

        with safe_open(str(path), "np") as f:
            found = f.metadata() or {}
            if any(found.get(k) != v for k, v in meta.items()):
                return None
            return f.get_tensor(name)
    except Exception:  # noqa: BLE001 - a corrupt cache entry is recomputed
        return None


def _write_tensor(path: Path, name: str, value: torch.Tensor, meta: dict[str, str]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    save_file({name: value.contiguous()}, str(tmp), metadata=meta)
    os.replace(tmp, path)


def _write_latents(path: Path, lat: torch.Tensor, vae_digest: str, clip_key: str) -> None:
    _write_tensor(path, "latents", lat, {"vae": vae_digest, "clip": clip_key})


class LatentWindows:
    """Windows of cached latents with their conditions, at mixed lengths (``clip.train_frames``).

    Every clip's latents and time-varying conditions are copied once into flat arrays, so a batch
    of windows is one index gather per field (:meth:`gather`), not a Python loop per sample. Only
    the flat arrays are kept: a clip's per-frame conditions (object embeddings, BEV, layout) take
    about 19 MB at the default preset, and a second copy of them all would double the memory a
    large dataset needs.
    """

    def __init__(
        self,
        clips: list[Clip],
        latents: list[torch.Tensor],
        cfg: ModelConfig,
        text_encoder: TextEncoder,
        image_encoder: ImageDescriptionEncoder | None,
        layouts: list[np.ndarray] | None = None,
    ) -> None:
        """``layouts``: each clip's layout raster when computed already (:func:`cached_layouts`)."""
        self.clips, self.cfg = clips, cfg
        layouts = layouts if layouts is not None else [None] * len(clips)
        self.lengths = np.array([c.num_frames for c in clips], dtype=np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(self.lengths)[:-1]]).astype(np.int64)
        self.flat_latents = torch.cat([lat.float() for lat in latents])  # (sum T, V, C, h, w)
        self.flat_time: dict[str, np.ndarray] = {}
        static: dict[str, list[np.ndarray]] = {}
        dit_cfg = without_label_decoder(cfg)  # the DiTs never read the decoder's label maps
        for i, (c, lay) in enumerate(zip(clips, layouts, strict=True)):
            options = ConditionOptions(image_encoder=image_encoder, crops=c.crops, crop_since=c.crop_since, layout=lay)
            arrays = build_condition_arrays(c.frames, np.asarray(c.bev), dit_cfg, text_encoder, options)
            rows = slice(self.offsets[i], self.offsets[i] + self.lengths[i])
            for k in ConditionArrays.TIME_FIELDS:
                value = getattr(arrays, k)
                if k not in self.flat_time:
                    self.flat_time[k] = np.empty((int(self.lengths.sum()), *value.shape[1:]), value.dtype)
                self.flat_time[k][rows] = value
            for f in fields(ConditionArrays):
                if f.name not in ConditionArrays.TIME_FIELDS:
                    static.setdefault(f.name, []).append(getattr(arrays, f.name))
        self.per_clip = {k: np.stack(v) for k, v in static.items()}
        # (sum T, 3): x, y, yaw of every frame's ego, for the ego condition relative to a window's start
        self.ego_pose = np.array([[f.ego.x, f.ego.y, f.ego.yaw] for c in clips for f in c.frames], dtype=np.float64)

    def clip_arrays(self, clip: int) -> ConditionArrays:
        """The whole of clip ``clip``'s condition arrays (views of the flat arrays; ego relative to
        the clip's first frame)."""
        rows = slice(self.offsets[clip], self.offsets[clip] + self.lengths[clip])
        return ConditionArrays(
            **{k: v[rows] for k, v in self.flat_time.items()}, **{k: v[clip] for k, v in self.per_clip.items()}
        )

    def window(self, clip: int, start: int, frames: int) -> tuple[torch.Tensor, ConditionArrays]:
        c, stop = self.clips[clip], start + frames
        arr = self.clip_arrays(clip).frames(start, stop)
        # The ego condition is relative to the first frame of the sequence the model sees.
        first = c.frames[start].ego
        ego = np.stack([fr.ego_pose_condition(first) for fr in c.frames[start:stop]]).astype(np.float32)
        offset = int(self.offsets[clip])
        return self.flat_latents[offset + start : offset + stop], replace(arr, ego=ego)

    def gather(self, clips: np.ndarray, frame_index: np.ndarray, anchor: np.ndarray) -> tuple[torch.Tensor, Conditions]:
        """x0 (B, T, V, C, h, w) float32 and conditions of frames ``frame_index`` (B, T) of ``clips``
        (B,), each row's ego relative to its frame ``anchor`` (B,) (:meth:`SceneFrame.ego_pose_condition`)."""
        clips = np.asarray(clips, dtype=np.int64)
        flat = self.offsets[clips][:, None] + np.asarray(frame_index, dtype=np.int64)
        x0 = self.flat_latents[torch.from_numpy(flat)]
        kw = {k: torch.from_numpy(v[flat]) for k, v in self.flat_time.items()}
        kw.update({k: torch.from_numpy(v[clips]) for k, v in self.per_clip.items()})
        kw["ego"] = torch.from_numpy(relative_ego(self.ego_pose[flat], self.ego_pose[self.offsets[clips] + anchor]))
        return x0, Conditions(**as_held(kw), drop=torch.zeros(len(clips), dtype=torch.bool))

    def windows(self, clips: np.ndarray, starts: np.ndarray, frames: int) -> tuple[torch.Tensor, Conditions]:
        """Windows [start, start + frames) of ``clips``, ego relative to each window's first frame."""
        starts = np.asarray(starts, dtype=np.int64)
        return self.gather(clips, starts[:, None] + np.arange(frames), starts)

    def draw(
        self, rng: np.random.Generator, batch: int, frames: int | None = None, pool: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """Random windows: (clips (B,), starts (B,), frames). ``frames`` fixes the length (default: drawn
        from ``clip.train_frames``; when every clip is shorter, the longest length available); ``pool``
        restricts the clips (default all)."""
        pool = np.arange(len(self.clips)) if pool is None else np.asarray(pool, dtype=np.int64)
        lengths = self.lengths[pool]
        t = int(rng.choice(self.cfg.clip.train_frames)) if frames is None else frames
        eligible = pool[lengths >= t]
        if len(eligible) == 0:  # every clip is shorter: use the longest available length
            t = int(lengths.max())
            eligible = pool[lengths == t]
        picks = rng.choice(eligible, size=batch)
        starts = rng.integers(self.lengths[picks] - t + 1)
        return picks, starts, t

    def sample(
        self, rng: np.random.Generator, batch: int, frames: int | None = None
    ) -> tuple[torch.Tensor, Conditions]:
        """x0 (B, T, V, C, h, w) and conditions of random windows (:meth:`draw`)."""
        picks, starts, t = self.draw(rng, batch, frames)
        return self.windows(picks, starts, t)


def relative_ego(poses: np.ndarray, first: np.ndarray) -> np.ndarray:
    """The paper's ego condition ``[R_t; t_t^T]`` (..., 4, 3) of poses (..., T, 3) = (x, y, yaw)
    relative to ``first`` (..., 3): :meth:`SceneFrame.ego_pose_condition`, vectorized."""
    yaw0 = first[..., None, 2]
    rel_yaw = wrap_angle(poses[..., 2] - yaw0)
    c0, s0 = np.cos(yaw0), np.sin(yaw0)
    dx, dy = poses[..., 0] - first[..., None, 0], poses[..., 1] - first[..., None, 1]
    c, s = np.cos(rel_yaw), np.sin(rel_yaw)
    zero, one = np.zeros_like(c), np.ones_like(c)
    rows = [
        np.stack([c, -s, zero], -1),
        np.stack([s, c, zero], -1),
        np.stack([zero, zero, one], -1),
        np.stack([c0 * dx + s0 * dy, -s0 * dx + c0 * dy, zero], -1),
    ]
    return np.stack(rows, -2).astype(np.float32)
