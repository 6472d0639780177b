"""Record the autopilot on the procedural backend and behaviour-clone the learned zoo members.

    python -m m4world_env.zoo.train_learned --out m4world_env/zoo/weights [--members NAME ...] [--workdir DIR]

Recording: episode ``i`` of the fixed list drives scenario ``i mod 9`` (every bundled scenario) in
one of the autopilot's driving styles, from seed ``FIRST_SEED + i`` (disjoint from the evaluation
seeds 0..999). A member with a budget of ``n`` episodes trains on episodes ``0 .. n-1``. Each step
stores the policy's inputs (:func:`~m4world_env.zoo.learned.extract_features`), the ego speed
and the autopilot's action. Episodes are cached as npz in ``--workdir`` under a key of the
recording recipe, so a second run reads them instead of driving again.

Robustness (DAgger-lite): in a fraction of the episodes the car executes the autopilot's action
plus slowly varying noise while the stored label stays the autopilot's clean action. The car then
drifts off the lane centre and off its speed, and the data shows how the autopilot recovers:
without it a cloned policy only ever sees perfect driving and cannot correct its own drift.

Training: one network per member, Adam on the mean squared error of the 2-d action, seeded with
the member's seed, on a fixed number of CPU threads; the same command writes the same weights.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from safetensors.torch import save_file

import m4world_env  # noqa: F401 (registers M4World-v0)
from m4world_env.policies import IDMAutopilot, driving_style
from m4world_env.scenario import list_scenarios
from m4world_env.zoo import learned
from m4world_env.zoo.base import SensorGeometry
from m4world_env.zoo.learned import LEARNED_SPECS, WEIGHTS_FORMAT, BehaviourCloningNet, LearnedSpec, extract_features

DEFAULT_WORKDIR = Path("runs/zoo_learned")
# Evaluation uses seeds 0..999: demonstrations start far above so no evaluated episode was seen.
FIRST_SEED = 10_000
STYLES = ("steady", "speed_changes", "lane_changes")
EPISODE_STEPS = 100  # 20 s at the scenarios' 5 Hz: long enough for lane changes and speed changes to play out
# Most episodes are driven with noise: a cloned policy's own small errors put it off the lane
# centre within seconds, and only the noisy episodes show the way back. The clean fifth keeps
# unperturbed driving, the distribution the policy starts from, in the data.
NOISY_FRACTION = 0.8
# Noise on the executed [acceleration, steering] action (normalized units): 0.2 is 1 m/s^2;
# 0.08 is 3.6 deg of wheel angle, which held for half a second moves the car about a metre
# sideways at highway speed: offsets the autopilot corrects within its own lane.
NOISE_STD = (0.2, 0.08)
# AR(1) correlation per 0.2 s step: about a second of memory, so the noise drifts the car
# rather than jittering it (white noise of this size averages out within a few steps).
NOISE_CORRELATION = 0.8

BATCH_SIZE = 64
# Peak rate of a cosine decay: high enough that the highway steering, a small signal beside the
# large steering of turns and roundabouts, is fitted within the members' few thousand steps.
LEARNING_RATE = 3e-3
# Fixed for training: CPU reductions may sum in another order with another thread count, and the
# weights must not depend on the machine's setting. One thread, because on a machine shared with
# other jobs, two OpenMP threads per process wait on each other and run many times slower.
TRAIN_THREADS = 1
# Mirror augmentation: each sample is flipped left-right (camera and LiDAR crop, both centred on
# straight ahead) with its steering label negated, with this probability. A mirrored road is a
# plausible road, and a net that has seen both sides cannot learn a steering bias: on a straight
# highway a bias of one degree takes the car into the next lane within two seconds.
MIRROR_PROBABILITY = 0.5
STEERING = 1  # the action's column that mirroring negates
# safetensors creates its file readable by its owner alone; the weights are package data that
# every user of an installed copy reads.
SHIPPED_FILE_MODE = 0o644
HEADER_SIZE_BYTES = 8  # a safetensors file starts with its JSON header's length, a little-endian u64
EVAL_CHUNK = 512  # samples per forward pass when measuring the final loss


@dataclass(frozen=True)
class RecordingRecipe:
    """What the recorded episodes are; every field enters the cache key."""

    episode_steps: int = EPISODE_STEPS
    first_seed: int = FIRST_SEED
    styles: tuple[str, ...] = STYLES
    scenarios: tuple[str, ...] = field(default_factory=lambda: tuple(list_scenarios()))
    noisy_fraction: float = NOISY_FRACTION
    noise_std: tuple[float, float] = NOISE_STD
    noise_correlation: float = NOISE_CORRELATION

    def key(self) -> str:
        """A short hash of the recipe and of the feature layout: a change to either records anew."""
        features = {
            "camera_view": learned.CAMERA_VIEW,
            "camera_shape": learned.CAMERA_SHAPE,
            "lidar_fov": learned.LIDAR_FOV_FRACTION,
            "lidar_columns": learned.LIDAR_COLUMNS,
            "speed_scale": learned.SPEED_SCALE,
        }
        text = json.dumps({"recipe": asdict(self), "features": features}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:12]

    def plan(self, index: int) -> tuple[str, str, int]:
        """Episode ``index``'s (scenario, style, seed). The style shifts by one each pass over the
        scenarios, so every scenario meets every style (with 9 scenarios and 3 styles a plain
        ``index mod 3`` would pair each scenario with one style forever)."""
        n = len(self.scenarios)
        style = self.styles[(index + index // n) % len(self.styles)]
        return self.scenarios[index % n], style, self.first_seed + index


def _make_env(scenario: str) -> gym.Env:
    return gym.make(
        "M4World-v0",
        scenario=scenario,
        backend="procedural",
        config={"observation_keys": ["cameras", "lidar"], "action_type": "continuous"},
    )


def record_episode(index: int, recipe: RecordingRecipe) -> dict[str, np.ndarray]:
    """Drive episode ``index`` with the autopilot. Returns the policy's inputs: camera uint8
    (T, 3, 32, 56) (the features' pixels times 255, exact), lidar float32 (T, 1, 32, 128), speed
    float32 (T, 1) (the speed feature); ego_speed float32 (T,) (m/s); action float32 (T, 2) (the
    autopilot's, the label); executed float32 (T, 2) (with the noise); noisy bool ()."""
    scenario, style, seed = recipe.plan(index)
    rng = np.random.default_rng(np.random.SeedSequence([seed, index]))
    noisy = bool(rng.random() < recipe.noisy_fraction)
    env = _make_env(scenario)
    try:
        geometry = SensorGeometry.of_env(env)
        autopilot = IDMAutopilot(driving_style(style), seed=seed)
        obs, info = env.reset(seed=seed)
        std = np.asarray(recipe.noise_std, dtype=np.float32)
        rho = recipe.noise_correlation
        noise = np.zeros(2, dtype=np.float32)
        keys = ("camera", "lidar", "speed", "ego_speed", "action", "executed")
        rows: dict[str, list[np.ndarray]] = {k: [] for k in keys}
        for _ in range(recipe.episode_steps):
            features = extract_features(obs, info["speed"], geometry)
            label = np.asarray(autopilot(env.unwrapped.bridge), dtype=np.float32)
            if noisy:
                noise = rho * noise + np.sqrt(1.0 - rho**2) * std * rng.standard_normal(2).astype(np.float32)
            executed = np.clip(label + noise, -1.0, 1.0).astype(np.float32)
            rows["camera"].append(np.round(features.camera * 255.0).astype(np.uint8))
            rows["lidar"].append(features.lidar)
            rows["speed"].append(features.speed)
            rows["ego_speed"].append(np.float32(info["speed"]))
            rows["action"].append(label)
            rows["executed"].append(executed)
            obs, _, terminated, truncated, info = env.step(executed)
            if terminated or truncated:
                break
    finally:
        env.close()
    out = {k: np.stack(v) for k, v in rows.items()}
    out["noisy"] = np.array(noisy)
    return out


def episode_file(workdir: Path, recipe: RecordingRecipe, index: int) -> Path:
    scenario, style, seed = recipe.plan(index)
    return workdir / f"demos-{recipe.key()}" / f"episode_{index:04d}_{scenario}_{style}_{seed}.npz"


def load_or_record(
    workdir: Path, recipe: RecordingRecipe, episodes: int, log: bool = True
) -> list[dict[str, np.ndarray]]:
    """Episodes ``0 .. episodes-1``, from the cache or recorded now (and cached, atomically)."""
    out = []
    for index in range(episodes):
        path = episode_file(workdir, recipe, index)
        if not path.is_file():
            data = record_episode(index, recipe)
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(path.name + f".tmp-{os.getpid()}.npz")
            np.savez_compressed(tmp, **data)
            os.replace(tmp, path)
            if log:
                print(f"  recorded {path.name}: {len(data['action'])} steps, noisy={bool(data['noisy'])}", flush=True)
        with np.load(path) as f:
            out.append({k: f[k] for k in f.files})
    return out


@dataclass(frozen=True)
class TrainResult:
    spec: LearnedSpec
    path: Path
    samples: int
    final_loss: float
    seconds: float


def _stack(episodes: list[dict[str, np.ndarray]]) -> dict[str, torch.Tensor]:
    return {
        "camera": torch.from_numpy(np.concatenate([e["camera"] for e in episodes])),
        "lidar": torch.from_numpy(np.concatenate([e["lidar"] for e in episodes])),
        "speed": torch.from_numpy(np.concatenate([e["speed"] for e in episodes])),
        "action": torch.from_numpy(np.concatenate([e["action"] for e in episodes])),
    }


def _inputs(data: dict[str, torch.Tensor], rows: torch.Tensor | slice) -> tuple[torch.Tensor, ...]:
    # uint8 / 255 in float32 is bit-identical to extract_features' pixels.
    return data["camera"][rows].to(torch.float32) / 255.0, data["lidar"][rows], data["speed"][rows]


def _mirror(
    camera: torch.Tensor, lidar: torch.Tensor, action: torch.Tensor, flip: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The batch with the rows where ``flip`` (B,) bool is set mirrored left-right: camera
    (B, 3, H, W) and lidar (B, 1, beams, columns) along their width, the steering negated."""
    image_rows = flip[:, None, None, None]
    action = action.clone()
    action[:, STEERING] = torch.where(flip, -action[:, STEERING], action[:, STEERING])
    return torch.where(image_rows, camera.flip(-1), camera), torch.where(image_rows, lidar.flip(-1), lidar), action


def _sort_header(path: Path) -> None:
    """Rewrite the JSON header of the safetensors file at ``path`` with its keys sorted, in place.
    safetensors writes the metadata in a hash map's order, which changes from process to process;
    sorted, the same weights make the same bytes and a rerun of ``make zoo`` leaves git clean."""
    with open(path, "r+b") as f:
        size = int.from_bytes(f.read(HEADER_SIZE_BYTES), "little")
        header = json.loads(f.read(size))
        text = json.dumps(header, sort_keys=True, separators=(",", ":")).encode()
        if len(text) > size:
            raise RuntimeError(f"{path}: the sorted safetensors header is longer than the original")
        f.seek(HEADER_SIZE_BYTES)
        f.write(text.ljust(size))  # the format pads its header with spaces


def train_member(spec: LearnedSpec, episodes: list[dict[str, np.ndarray]], out_dir: Path) -> TrainResult:
    """Train ``spec``'s network on ``episodes`` and write ``<out_dir>/<name>.safetensors``."""
    start = time.perf_counter()
    data = _stack(episodes)
    n = len(data["action"])
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(TRAIN_THREADS)
    try:
        torch.manual_seed(spec.seed)
        generator = torch.Generator().manual_seed(spec.seed)
        net = BehaviourCloningNet(spec.sensors)
        optimizer = torch.optim.Adam(net.parameters(), lr=LEARNING_RATE)
        # Cosine decay to zero: the last steps settle instead of bouncing at the full rate.
        schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=spec.train_steps)
        net.train()
        for _ in range(spec.train_steps):
            rows = torch.randint(0, n, (BATCH_SIZE,), generator=generator)
            camera, lidar, speed = _inputs(data, rows)
            target = data["action"][rows]
            flip = torch.rand(BATCH_SIZE, generator=generator) < MIRROR_PROBABILITY
            camera, lidar, target = _mirror(camera, lidar, target, flip)
            loss = torch.nn.functional.mse_loss(net(camera, lidar, speed), target)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            schedule.step()
        net.eval()
        with torch.no_grad():
            total = sum(
                torch.nn.functional.mse_loss(
                    net(*_inputs(data, slice(i, i + EVAL_CHUNK))), data["action"][i : i + EVAL_CHUNK], reduction="sum"
                ).item()
                for i in range(0, n, EVAL_CHUNK)
            )
        final_loss = total / (2 * n)  # the mean squared error per action entry on the training set
    finally:
        torch.set_num_threads(previous_threads)
    metadata = {
        "format": WEIGHTS_FORMAT,
        "name": spec.name,
        "version": str(spec.version),
        "seed": str(spec.seed),
        "sensors": spec.sensors,
        "episodes": str(len(episodes)),
        "samples": str(n),
        "train_steps": str(spec.train_steps),
        "final_loss": f"{final_loss:.6g}",
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    path = learned.weights_path(spec, out_dir)
    tmp = path.with_name(path.name + f".tmp-{os.getpid()}")
    save_file({k: v.contiguous() for k, v in net.state_dict().items()}, str(tmp), metadata=metadata)
    _sort_header(tmp)
    tmp.chmod(SHIPPED_FILE_MODE)
    os.replace(tmp, path)
    return TrainResult(spec, path, n, final_loss, time.perf_counter() - start)


def train(
    specs: Sequence[LearnedSpec],
    out_dir: Path,
    workdir: Path = DEFAULT_WORKDIR,
    recipe: RecordingRecipe | None = None,
    log: bool = True,
) -> list[TrainResult]:
    """Record (or read from the cache) the largest budget of ``specs`` once, then train each."""
    recipe = recipe or RecordingRecipe()
    start = time.perf_counter()
    episodes = load_or_record(Path(workdir), recipe, max(s.episodes for s in specs), log=log)
    recorded = time.perf_counter() - start
    if log:
        print(
            f"demonstrations: {len(episodes)} episodes, {sum(len(e['action']) for e in episodes)} steps, "
            f"{recorded:.1f} s",
            flush=True,
        )
    results = []
    for spec in specs:
        result = train_member(spec, episodes[: spec.episodes], Path(out_dir))
        results.append(result)
        if log:
            print(
                f"  {spec.name}: {result.samples} samples, {spec.train_steps} steps, "
                f"final loss {result.final_loss:.5f}, {result.seconds:.1f} s, "
                f"{result.path.stat().st_size / 1024:.0f} KB",
                flush=True,
            )
    if log:
        training = sum(r.seconds for r in results)
        print(f"training {training:.1f} s; total {time.perf_counter() - start:.1f} s", flush=True)
    return results


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    names = [s.name for s in LEARNED_SPECS]
    parser = argparse.ArgumentParser(
        prog="python -m m4world_env.zoo.train_learned",
        description="Record autopilot demonstrations and behaviour-clone the learned zoo members.",
    )
    parser.add_argument("--out", type=Path, required=True, help="folder for <member>.safetensors")
    parser.add_argument("--members", nargs="+", metavar="NAME", help=f"members to train (default: all of {names})")
    parser.add_argument("--workdir", type=Path, default=DEFAULT_WORKDIR, help="cache of recorded episodes")
    args = parser.parse_args(argv)
    for flag, path in (("--out", args.out), ("--workdir", args.workdir)):
        if path.exists() and not path.is_dir():
            parser.error(f"{flag} {path}: exists and is not a folder")
    unknown = [m for m in args.members or [] if m not in names]
    if unknown:
        parser.error(f"--members {' '.join(unknown)}: unknown member(s); choose from {names}")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    wanted = set(args.members or [s.name for s in LEARNED_SPECS])
    specs = [s for s in LEARNED_SPECS if s.name in wanted]
    train(specs, args.out, args.workdir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
