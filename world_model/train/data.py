"""Training data: random sensor frames for the VAE, cached latent windows + conditions for the DiT."""

from __future__ import annotations

import hashlib
import os
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from world_model.data import Clip, iter_clips
from world_model.data.clips import clip_fingerprint
from world_model.model.conditions import ConditionArrays, Conditions, build_condition_arrays
from world_model.model.config import ModelConfig
from world_model.model.imagedesc import ImageDescriptionEncoder
from world_model.model.reference import ReferenceConfig
from world_model.model.text import TextEncoder
from world_model.model.vae import SensorVAE, cameras_to_images, lidar_to_images
from world_model.scene import SceneFrame

NEAR_PLANE_M = ReferenceConfig().near_plane_m  # boxes clipped as the simulator and the reference masks do


def load_clips(data_dir: str | Path, cfg: ModelConfig) -> list[Clip]:
    """All clips of a dataset, checked against the model's sensors."""
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


def object_pixel_weights(frame: SceneFrame, view: int, height: int, width: int, extra: float) -> np.ndarray:
    """(H, W) float32 loss weights of camera ``view``: 1 everywhere, ``1 + extra`` inside the
    projected 3-D box of every object in view (where small objects live, which plain L1 ignores)."""
    out = np.ones((height, width), np.float32)
    if extra == 0.0 or not frame.objects:
        return out
    corners = frame.object_corners_lidar()
    for o in range(len(frame.objects)):
        box = frame.rig.cameras[view].box_extent(corners[o], NEAR_PLANE_M)
        if box is not None:
            x0, y0, x1, y1 = box
            out[y0:y1, x0:x1] = 1.0 + extra
    return out


class FrameSampler:
    """Random (clip, frame, view) images for the VAE; view == num_cameras is the LiDAR map."""

    def __init__(self, clips: list[Clip], cfg: ModelConfig) -> None:
        self.clips, self.cfg = clips, cfg

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
        return torch.from_numpy(object_pixel_weights(fr, view, s.height, s.width, extra))[None]

    def sample(self, rng: np.random.Generator, batch: int) -> FrameBatch:
        """``batch`` random images of random clips, frames and views (cameras or the LiDAR map)."""
        ci = rng.integers(len(self.clips), size=batch)
        fi = [int(rng.integers(self.clips[c].num_frames)) for c in ci]
        vi = rng.integers(self.cfg.sensors.num_views, size=batch)
        picks = list(zip(ci.tolist(), fi, vi.tolist(), strict=True))
        return FrameBatch(
            torch.stack([self.image(*p) for p in picks]),
            torch.as_tensor(vi == self.cfg.sensors.lidar_view),
            torch.stack([self.weights(*p) for p in picks]),
        )

    def eval_frames(self, count: int) -> list[tuple[int, int]]:
        """Up to ``count`` (clip, frame) pairs spread over the dataset (deterministic)."""
        pairs = [(ci, f) for ci, c in enumerate(self.clips) for f in range(c.num_frames)]
        idx = np.linspace(0, len(pairs) - 1, num=min(count, len(pairs))).round().astype(int)
        return [pairs[i] for i in sorted(set(idx.tolist()))]


def file_digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def latent_cache_dir(run_dir: str | Path) -> Path:
    """The run's one latent cache, shared by every stage that encodes clips (teacher, student
    stages, reference, LoRA): entries are keyed by clip name, clip fingerprint and VAE digest."""
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
    lat = vae.encode_frames(np.asarray(clip.cameras), np.asarray(clip.lidar, dtype=np.float32))
    _write_latents(path, lat, vae_digest, key)
    return lat


def _write_latents(path: Path, lat: torch.Tensor, vae_digest: str, clip_key: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    save_file({"latents": lat.contiguous()}, str(tmp), metadata={"vae": vae_digest, "clip": clip_key})
    os.replace(tmp, path)


class LatentWindows:
    """Windows of cached latents with their conditions, at mixed lengths (``clip.train_frames``)."""

    def __init__(
        self,
        clips: list[Clip],
        latents: list[torch.Tensor],
        cfg: ModelConfig,
        text_encoder: TextEncoder,
        image_encoder: ImageDescriptionEncoder | None,
    ) -> None:
        self.clips, self.latents, self.cfg = clips, latents, cfg
        self.arrays: list[ConditionArrays] = [
            build_condition_arrays(
                c.frames, np.asarray(c.bev), cfg, text_encoder, image_encoder, c.crops, crop_since=c.crop_since
            )
            for c in clips
        ]

    def window(self, clip: int, start: int, frames: int) -> tuple[torch.Tensor, ConditionArrays]:
        c, stop = self.clips[clip], start + frames
        arr = self.arrays[clip].frames(start, stop)
        # The ego condition is relative to the first frame of the sequence the model sees.
        first = c.frames[start].ego
        ego = np.stack([fr.ego_pose_condition(first) for fr in c.frames[start:stop]]).astype(np.float32)
        return self.latents[clip][start:stop], replace(arr, ego=ego)

    def sample(self, rng: np.random.Generator, batch: int) -> tuple[torch.Tensor, Conditions]:
        """x0 (B, T, V, C, h, w) and conditions; T drawn from ``clip.train_frames`` per batch."""
        lengths = [c.num_frames for c in self.clips]
        t = int(rng.choice(self.cfg.clip.train_frames))
        eligible = [i for i, n in enumerate(lengths) if n >= t]
        if not eligible:  # every clip is shorter: use the longest available length
            t = max(lengths)
            eligible = [i for i, n in enumerate(lengths) if n == t]
        picks = rng.choice(eligible, size=batch)
        items = [self.window(int(ci), int(rng.integers(lengths[ci] - t + 1)), t) for ci in picks]
        x0 = torch.stack([x for x, _ in items]).float()
        return x0, Conditions.collate([a for _, a in items])
