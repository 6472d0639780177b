"""Small structured synthetic clips for model/training tests (not noise: overfitting is measurable)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from world_model import Box3D, EgoState, MapGeometry, SceneFrame, SceneObject, ScenePrompt
from world_model.data import Clip, write_clip
from world_model.model import ModelConfig
from world_model.train.run import StageRuntime

QUIET = StageRuntime(progress=False)  # a training stage without a progress bar


def make_frames(cfg: ModelConfig, num_frames: int, num_objects: int = 3, seed: int = 0) -> list[SceneFrame]:
    """A straight drive with ``num_objects`` cars ahead/beside, 10 Hz."""
    rng = np.random.default_rng(seed)
    rig = cfg.sensors.rig()
    prompt = ScenePrompt(text="a highway with light traffic", weather="sunny", time_of_day="day")
    colors = ["red", "blue", "white", "black", "green"]
    starts = [(float(rng.uniform(8, 40)), float(rng.choice([-4.0, 0.0, 4.0]))) for _ in range(num_objects)]
    frames = []
    for f in range(num_frames):
        ego = EgoState(x=2.0 * f, y=0.0, yaw=0.0, speed=20.0)
        objs = tuple(
            SceneObject(
                track_id=f"car{i}",
                category="car" if i % 2 == 0 else "truck",
                box=Box3D(center=(x0 + 1.5 * f, y0, 0.8), size=(4.5, 1.9, 1.6), yaw=0.0),
                color_name=colors[i % len(colors)],
                description="" if i == 0 else f"a {colors[i % len(colors)]} vehicle",
            )
            for i, (x0, y0) in enumerate(starts)
        )
        frames.append(
            SceneFrame(
                time=0.1 * f,
                frame_index=f,
                ego=ego,
                objects=objs,
                map=MapGeometry(),
                prompt=prompt,
                rig=rig,
                lidar=cfg.sensors.lidar,
                bev=cfg.sensors.bev,
            )
        )
    return frames


def make_sensors(cfg: ModelConfig, num_frames: int, phase: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """cameras uint8 (T, V, H, W, 3), lidar float16 (T, B, A) metres, bev uint8 (T, h, w, c).

    Cameras: sky/road split plus stripes that move with the frame index, tinted per view.
    LiDAR: road ranges growing with elevation, no return (0) above the horizon, a moving object.
    """
    s = cfg.sensors
    t_idx = np.arange(num_frames)[:, None, None, None]
    v_idx = np.arange(s.num_cameras)[None, :, None, None]
    rows = np.arange(s.height)[None, None, :, None]
    cols = np.arange(s.width)[None, None, None, :]
    sky = rows < s.height // 2
    stripes = np.sin(2 * np.pi * (cols / 16.0 - 0.15 * t_idx + phase) + v_idx) > 0
    base = np.where(sky, 180, 60 + 80 * stripes)
    cams = np.stack([base + 10 * v_idx, base, np.where(sky, 230, base - 20 * v_idx % 40)], axis=-1)
    cams = np.clip(np.broadcast_to(cams, (num_frames, s.num_cameras, s.height, s.width, 3)), 0, 255).astype(np.uint8)

    spec = s.lidar
    el = spec.elevations()[None, :, None]
    az = spec.azimuths()[None, None, :]
    ground = np.where(el < -0.01, spec.mount_height / np.maximum(np.sin(-el), 1e-3), 0.0)
    ground = np.minimum(ground, spec.max_range * 0.9) * np.ones_like(az)
    obj_az = 0.3 * np.sin(0.2 * np.arange(num_frames) + phase)[:, None, None]
    obj = (np.abs(az - obj_az) < 0.2) & (el > -0.2) & (el < 0.05)
    lidar = np.where(obj, 15.0, ground).astype(np.float16)
    lidar = np.broadcast_to(lidar, (num_frames, spec.beams, spec.azimuth)).copy()

    h, w, c = s.bev.shape
    bev = np.zeros((num_frames, h, w, c), np.uint8)
    bev[:, :, w // 4 : 3 * w // 4, 0] = 1
    for k in range(c - 1):
        bev[:, :, w // 4 + (k + 1) * w // 8, k + 1] = 1
    return cams, lidar, bev


def make_dataset(root: str | Path, cfg: ModelConfig, lengths: tuple[int, ...] = (4, 3)) -> Path:
    """A dataset of clips of the given lengths (mixed lengths on purpose), with one crop per track."""
    root = Path(root)
    for i, n in enumerate(lengths):
        frames = make_frames(cfg, n, seed=i)
        cams, lidar, bev = make_sensors(cfg, n, phase=0.37 * i)
        crops = {f"car{k}": np.full((12, 10, 3), 40 * k + 20, np.uint8) for k in range(2)}
        write_clip(root, Clip(f"clip{i:02d}", frames, cams, lidar, bev, crops))
    return root


def tiny_conditions(cfg: ModelConfig, num_frames: int, batch: int = 1, num_objects: int = 3):
    """Conditions (hash text encoder, no image encoder) for synthetic frames."""
    from world_model.model import Conditions, build_condition_arrays, make_text_encoder

    enc = make_text_encoder(cfg.text)
    items = []
    for b in range(batch):
        frames = make_frames(cfg, num_frames, num_objects=num_objects, seed=b)
        _, _, bev = make_sensors(cfg, num_frames)
        items.append(build_condition_arrays(frames, bev, cfg, enc))
    return Conditions.collate(items)


def perturbed(module, seed: int = 0, scale: float = 0.2):
    """Add noise to every parameter: zero-initialized gates/heads would make outputs trivially constant."""
    import torch

    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.add_(scale * torch.randn(p.shape, generator=gen))
    return module.eval()


# A training process that SIGKILLs itself right after writing checkpoint STEP: no exit handler or
# finally block runs, as when a machine's job is killed, and where it stops does not depend on timing.
KILLED_AFTER_CHECKPOINT = """
import os, signal, sys
import world_model.train.trainer as trainer
from world_model.train.cli import main

save, step = trainer.save_checkpoint, int(sys.argv[1])

def save_then_die(root, at, *args, **kwargs):
    path = save(root, at, *args, **kwargs)
    if at >= step:
        os.kill(os.getpid(), signal.SIGKILL)
    return path

trainer.save_checkpoint = save_then_die
sys.exit(main(sys.argv[2:]))
"""


def kill_after_checkpoint(train_args: list[str], checkpoints: Path, step: int = 4, timeout_s: float = 600.0) -> None:
    """Run ``python -m world_model.train *train_args`` in its own process, SIGKILLed right after it
    has written checkpoint ``step`` (``checkpoints/latest.json`` then names it): a run killed
    mid-way. ``timeout_s`` only bounds a run that hangs."""
    import json
    import os
    import signal
    import subprocess
    import sys

    src = Path(__file__).resolve().parents[1]
    cmd = [sys.executable, "-c", KILLED_AFTER_CHECKPOINT, str(step), *train_args]
    env = {**os.environ, "PYTHONPATH": str(src)}
    status = subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, timeout=timeout_s)
    if status.returncode != -signal.SIGKILL:
        raise AssertionError(f"the training run was not killed (status {status.returncode}): {status.stderr[-2000:]}")
    assert json.loads((checkpoints / "latest.json").read_text())["step"] == step


def train_cli(*args: str) -> dict:
    """``python -m world_model.train *args --preset tiny --no-progress`` in a subprocess; its summary."""
    import json
    import os
    import subprocess
    import sys

    src = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(src), "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "world_model.train", *args, "--preset", "tiny", "--no-progress"]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout)


def one_streamed_chunk(student, scfg, batch: int = 2):  # noqa: ANN201 - a torch.Tensor
    """The first chunk an exported ``student`` streams with its student config ``scfg`` after an
    all-zero first frame, under synthetic conditions: (batch, 1, V, C, h, w)."""
    import torch

    from world_model.student import StreamingEngine

    cond = tiny_conditions(student.cfg, 2, batch=batch)
    engine = StreamingEngine(student, scfg, torch.Generator().manual_seed(0))
    with torch.no_grad():
        engine.start(torch.zeros(batch, *student.cfg.latent_shape(1)), cond.frames(0, 1))
        return engine.step(cond.frames(1, 2))
