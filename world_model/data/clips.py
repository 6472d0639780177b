"""On-disk clip format written by ``m4world record`` and read by every training stage.

Layout (format ``m4world-clips``, version 1)::

    DATASET/
      dataset.json                 {"format", "version", "clips": [name, ...]}   (rewritten as clips land)
      <clip name>/
        meta.json                  scenario, seed, fps, num_frames, camera names, "static" (map,
                                   prompt, rig, lidar spec, bev spec: SceneFrame.static_dict()),
                                   optional "crop_since": {track id: first frame index its crop
                                   conditions} (absent: every frame)
        frames.jsonl               one SceneFrame per line, without the static parts
        cameras.npy                uint8   (T, V, H, W, 3), views in rig order
        lidar.npy                  float16 (T, beams, azimuth) metres; no return = 0.0
        bev.npy                    uint8   (T, h, w, c) {0,1} BEV map raster
        crops.npz                  optional: one uint8 (h, w, 3) reference crop per track id
                                   (the object's "image description", §3.2)

A clip is written into ``<name>.partial/`` and renamed when complete, so a killed recorder
leaves no half clip behind and a restarted one skips the clips that exist.
``.npy`` files are memory-mapped on read, so a dataset larger than RAM still loads.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from world_model.scene import SceneFrame

FORMAT_NAME = "m4world-clips"
FORMAT_VERSION = 1


class DatasetFormatError(ValueError):
    """A dataset directory or clip that does not follow the documented format."""


@dataclass
class Clip:
    """One recorded clip. Arrays may be memory-mapped (read-only)."""

    name: str
    frames: list[SceneFrame]
    cameras: np.ndarray  # uint8 (T, V, H, W, 3)
    lidar: np.ndarray  # float16/float32 (T, beams, azimuth)
    bev: np.ndarray  # uint8 (T, h, w, c)
    crops: dict[str, np.ndarray] = field(default_factory=dict)  # per track id: its reference crop
    meta: dict = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return len(self.frames)

    @property
    def fps(self) -> float:
        return float(self.meta["fps"])

    @property
    def crop_since(self) -> dict[str, int]:
        """Per track, the frame index from which its crop conditions the model (empty: all frames)."""
        return {k: int(v) for k, v in self.meta.get("crop_since", {}).items()}


def sha256_file(path: Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def write_json_atomic(path: Path, obj: object) -> None:
    """Write JSON so a reader never sees a half file (write aside, fsync, rename); the aside file
    is the writing process's own, so that writers in several processes never share one."""
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=1)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def write_clip(root: str | Path, clip: Clip, register: bool = True) -> Path:
    """Write ``clip`` atomically into ``root/clip.name`` and, with ``register``, list it in
    ``dataset.json`` (writers in parallel processes leave that to one process:
    :func:`register_clip`). ``clip.meta`` joins the written ``meta.json`` over the keys the format
    derives from the clip. Returns the clip dir."""
    name, frames, cameras, lidar, bev, crops = clip.name, clip.frames, clip.cameras, clip.lidar, clip.bev, clip.crops
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    t = len(frames)
    if t == 0:
        raise ValueError("a clip needs at least one frame")
    for arr_name, arr, ndim in (("cameras", cameras, 5), ("lidar", lidar, 3), ("bev", bev, 4)):
        if arr.ndim != ndim or arr.shape[0] != t:
            raise ValueError(f"{arr_name} must have {ndim} dims and {t} frames, got shape {arr.shape}")
    final = root / name
    partial = root / f"{name}.partial"
    if partial.exists():
        shutil.rmtree(partial)
    partial.mkdir()
    first = frames[0]
    fps = 1.0 / (frames[1].time - frames[0].time) if t > 1 else 10.0
    meta = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "name": name,
        "scenario": first.scenario,
        "num_frames": t,
        "fps": round(fps, 6),
        "camera_names": list(first.rig.names),
        "static": first.static_dict(),
        **clip.meta,
    }
    with open(partial / "frames.jsonl", "w") as f:
        for fr in frames:
            f.write(json.dumps(fr.to_dict(include_static=False)) + "\n")
    np.save(partial / "cameras.npy", np.ascontiguousarray(cameras, dtype=np.uint8))
    np.save(partial / "lidar.npy", np.ascontiguousarray(lidar, dtype=np.float16))
    np.save(partial / "bev.npy", np.ascontiguousarray(bev, dtype=np.uint8))
    if crops:
        np.savez_compressed(partial / "crops.npz", **{k: np.asarray(v, dtype=np.uint8) for k, v in crops.items()})
    write_json_atomic(partial / "meta.json", meta)
    if final.exists():
        shutil.rmtree(final)
    os.replace(partial, final)
    if register:
        register_clip(root, name)
    return final


def register_clip(root: str | Path, name: str) -> None:
    """Append clip ``name`` to ``dataset.json``'s recording order, unless it is listed already.
    Several processes may record into one dataset (``m4world record`` runs side by side): each
    read-modify-write of the index holds an exclusive lock, so no clip is lost from it."""
    root = Path(root)
    index_path = root / "dataset.json"
    with open(root / "dataset.json.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        index = (
            _read_index(root)
            if index_path.exists()
            else {"format": FORMAT_NAME, "version": FORMAT_VERSION, "clips": []}
        )
        if name not in index["clips"]:
            index["clips"].append(name)
            write_json_atomic(index_path, index)


def sort_index(root: str | Path) -> list[str]:
    """Put ``dataset.json``'s clips in name order: the order of a dataset written by processes
    side by side, whose recording order depends on their timing. Returns the clips."""
    root = Path(root)
    index = _read_index(root)
    index["clips"] = sorted(index["clips"])
    write_json_atomic(root / "dataset.json", index)
    return index["clips"]


def _read_index(root: Path) -> dict:
    path = root / "dataset.json"
    try:
        index = json.loads(path.read_text())
    except FileNotFoundError as e:
        raise DatasetFormatError(f"{root} is not an m4world dataset: {path.name} is missing") from e
    except json.JSONDecodeError as e:
        raise DatasetFormatError(f"{path} is not valid JSON: {e}") from e
    if index.get("format") != FORMAT_NAME:
        raise DatasetFormatError(f"{path}: format is {index.get('format')!r}, expected {FORMAT_NAME!r}")
    if index.get("version") != FORMAT_VERSION:
        raise DatasetFormatError(f"{path}: version {index.get('version')} not supported (expected {FORMAT_VERSION})")
    return index


def clip_exists(root: str | Path, name: str) -> bool:
    """True when a complete clip of this name is on disk (used by resumable recording)."""
    return (Path(root) / name / "meta.json").exists()


def list_clips(root: str | Path) -> list[str]:
    """Names of the complete clips of a dataset, in recording order."""
    root = Path(root)
    return [n for n in _read_index(root)["clips"] if clip_exists(root, n)]


def read_clip(root: str | Path, name: str, mmap: bool = True) -> Clip:
    """Load one clip; arrays are memory-mapped unless ``mmap=False``."""
    clip_dir = Path(root) / name
    meta_path = clip_dir / "meta.json"
    if not meta_path.exists():
        raise DatasetFormatError(f"clip {clip_dir} is incomplete or missing (no meta.json)")
    meta = json.loads(meta_path.read_text())
    static = meta["static"]
    # Parse the shared parts once; every frame then references the same objects.
    shared = SceneFrame.from_dict(
        {"time": 0, "frame_index": 0, "ego": {"x": 0, "y": 0, "yaw": 0}, "objects": []}, static
    )
    static_objs = {
        "map": shared.map,
        "prompt": shared.prompt,
        "rig": shared.rig,
        "lidar": shared.lidar,
        "bev": shared.bev,
    }
    with open(clip_dir / "frames.jsonl") as f:
        frames = [SceneFrame.from_dict(json.loads(line), static_objs) for line in f if line.strip()]
    mode = "r" if mmap else None
    cameras = np.load(clip_dir / "cameras.npy", mmap_mode=mode)
    lidar = np.load(clip_dir / "lidar.npy", mmap_mode=mode)
    bev = np.load(clip_dir / "bev.npy", mmap_mode=mode)
    crops: dict[str, np.ndarray] = {}
    if (clip_dir / "crops.npz").exists():
        with np.load(clip_dir / "crops.npz") as z:
            crops = {k: z[k] for k in z.files}
    if cameras.shape[0] != len(frames) or lidar.shape[0] != len(frames):
        raise DatasetFormatError(
            f"clip {clip_dir}: {len(frames)} frames but cameras {cameras.shape} / lidar {lidar.shape}"
        )
    return Clip(name=name, frames=frames, cameras=cameras, lidar=lidar, bev=bev, crops=crops, meta=meta)


def iter_clips(root: str | Path, mmap: bool = True) -> Iterator[Clip]:
    for name in list_clips(root):
        yield read_clip(root, name, mmap=mmap)


def clip_fingerprint(clip: Clip) -> str:
    """Identity of a recording: its metadata (scenario, seed, fps, frames, sensors) and array shapes."""
    blob = json.dumps([clip.meta, list(clip.cameras.shape), list(clip.lidar.shape)], sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]
