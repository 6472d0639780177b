"""Resumable, atomic checkpoints: safetensors weights + JSON metadata + optimizer/RNG state.

Layout of a checkpoint root::

    latest.json            {"step": N, "dir": "step_0000000N"}   (rewritten atomically)
    step_0000000N/         model.safetensors, ema.safetensors, ... , train_state.pt, meta.json

A checkpoint directory is written under a temporary name and renamed when complete; only then
does ``latest.json`` move to it. A process killed at any instant therefore leaves either the
previous checkpoint or the new one as "latest", never a half-written one. Older checkpoints
beyond ``keep`` and stale temporary directories are removed after each save.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from world_model.data.clips import write_json_atomic

LATEST = "latest.json"
STEP_PREFIX = "step_"
TMP_PREFIX = ".tmp-"


@dataclass
class Checkpoint:
    step: int
    path: Path
    tensors: dict[str, dict[str, torch.Tensor]]  # file stem -> state dict
    train_state: dict  # optimizer state, torch RNG state, ...
    meta: dict  # JSON metadata (config, numpy RNG state, metrics)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def save_checkpoint(
    root: str | Path,
    step: int,
    tensors: dict[str, dict[str, torch.Tensor]],
    train_state: dict,
    meta: dict,
    keep: int = 2,
) -> Path:
    """Write checkpoint ``step`` under ``root`` atomically and make it the latest."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    name = f"{STEP_PREFIX}{step:08d}"
    tmp = root / f"{TMP_PREFIX}{name}-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    for stem, state in tensors.items():
        save_file({k: v.detach().contiguous().cpu() for k, v in state.items()}, str(tmp / f"{stem}.safetensors"))
    torch.save(train_state, tmp / "train_state.pt")
    with open(tmp / "meta.json", "w") as f:
        json.dump({**meta, "step": step}, f, indent=1)
        f.flush()
        os.fsync(f.fileno())
    _fsync_dir(tmp)
    final = root / name
    if final.exists():  # a previous run died after the rename but before latest.json moved
        shutil.rmtree(final)
    os.replace(tmp, final)
    write_json_atomic(root / LATEST, {"step": step, "dir": name})
    _prune(root, keep, current=name)
    return final


def _prune(root: Path, keep: int, current: str) -> None:
    steps = sorted(p for p in root.iterdir() if p.is_dir() and p.name.startswith(STEP_PREFIX))
    for old in steps[: max(0, len(steps) - keep)]:
        if old.name != current:
            shutil.rmtree(old, ignore_errors=True)
    for stale in root.glob(f"{TMP_PREFIX}*"):
        shutil.rmtree(stale, ignore_errors=True)


def load_latest(root: str | Path) -> Checkpoint | None:
    """The checkpoint ``latest.json`` points to, or None when there is none yet."""
    root = Path(root)
    pointer = root / LATEST
    if not pointer.exists():
        return None
    try:
        info = json.loads(pointer.read_text())
        path, step = root / info["dir"], int(info["step"])
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError) as e:
        raise ValueError(
            f"{pointer} is corrupt ({e!r}): a checkpoint pointer holds {{'dir': ..., 'step': ...}}; "
            f"delete {pointer} to resume from the checkpoints' folder anew"
        ) from None
    if not path.is_dir():
        raise FileNotFoundError(f"{pointer} points to {path}, which is missing; delete {pointer} to restart")
    tensors = {p.stem: load_file(str(p)) for p in sorted(path.glob("*.safetensors"))}
    train_state = torch.load(path / "train_state.pt", map_location="cpu", weights_only=True)
    meta = json.loads((path / "meta.json").read_text())
    return Checkpoint(step=step, path=path, tensors=tensors, train_state=train_state, meta=meta)


def export_weights(path: str | Path, state: dict[str, torch.Tensor], config: dict) -> None:
    """Write a final model (``<path>.safetensors`` + ``<path>.json`` config) atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f"{TMP_PREFIX}{os.getpid()}.safetensors")
    save_file({k: v.detach().contiguous().cpu() for k, v in state.items()}, str(tmp))
    os.replace(tmp, path.with_suffix(".safetensors"))
    write_json_atomic(path.with_suffix(".json"), config)
