"""Ground-truth material for training and measuring the segmenter: camera views of recorded clips
with their scene label maps.

Label maps come from each clip's scene frames (:func:`~world_model.eval.scene_iou.scene_labels`,
no re-rendering of the images); they are computed once per clip and cached in a folder of the
caller's choosing (never inside the dataset, which may be read-only), keyed by the clip's
fingerprint so that a re-recorded clip is never paired with stale labels.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from world_model.data import Clip, list_clips, read_clip
from world_model.data.clips import clip_fingerprint
from world_model.eval.scene_iou import scene_labels


def cached_scene_labels(clip: Clip, cache_dir: str | Path) -> np.ndarray:
    """(T, V, H, W) uint8 scene labels of every frame of ``clip``, from ``cache_dir`` when there
    (memory-mapped), else computed and written there atomically."""
    h, w = clip.cameras.shape[2:4]
    path = Path(cache_dir) / f"{clip.name}-{clip_fingerprint(clip)}.npy"
    if path.exists():
        labels = np.load(path, mmap_mode="r")
        if labels.shape == clip.cameras.shape[:4]:
            return labels
    labels = scene_labels(clip.frames, h, w)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        np.save(f, labels)
    os.replace(tmp, path)
    return labels


@dataclass(frozen=True)
class ClipRef:
    """One clip of a dataset folder."""

    root: Path
    name: str


def clip_refs(roots: Sequence[str | Path], max_clips: int | None = None) -> list[ClipRef]:
    """The clips of every dataset folder, in folder order then ``dataset.json`` order (the first
    ``max_clips`` of each folder when given)."""
    refs = []
    for root in roots:
        names = list_clips(root)
        if not names:
            raise ValueError(f"{root}: the dataset lists no clips (record some with `m4world record --out {root}`)")
        refs += [ClipRef(Path(root), n) for n in names[:max_clips]]
    return refs


@dataclass(frozen=True)
class ViewSet:
    """Camera views and their labels, flattened over clips, frames and cameras."""

    images: np.ndarray  # (N, H, W, 3) uint8
    labels: np.ndarray  # (N, H, W) uint8 SCENE_CLASSES ids
    clip: np.ndarray  # (N,) int64 index into ``clips``
    clips: tuple[str, ...]


def collect_views(refs: Sequence[ClipRef], cache_dir: str | Path, frame_stride: int) -> ViewSet:
    """Every camera view of every ``frame_stride``-th frame of the clips ``refs``, loaded into memory."""
    if frame_stride < 1:
        raise ValueError(f"frame_stride must be >= 1, got {frame_stride}")
    if not refs:
        raise ValueError("collect_views needs at least one clip")
    images, labels, owner = [], [], []
    for i, ref in enumerate(refs):
        clip = read_clip(ref.root, ref.name)
        lab = cached_scene_labels(clip, cache_dir)
        frames = slice(0, clip.num_frames, frame_stride)
        cams = np.asarray(clip.cameras[frames])
        images.append(cams.reshape(-1, *cams.shape[2:]))
        labels.append(np.asarray(lab[frames]).reshape(-1, *lab.shape[2:]))
        owner.append(np.full(len(images[-1]), i, dtype=np.int64))
    return ViewSet(np.concatenate(images), np.concatenate(labels), np.concatenate(owner), tuple(r.name for r in refs))
