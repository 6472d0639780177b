"""Dataset recorder: scenarios → traffic bridge → procedural sensors → clips on disk.

``m4world record --scenario highway_sunny_day --episodes 8 --out data/train`` runs each scenario with an
autopilot ego (lane and speed changes; ``--styles`` mixes driving styles that brake, accelerate,
change lanes and weave: :data:`~m4world_env.policies.DRIVING_STYLES`) and seeded randomization of
traffic, colours, categories, weather and time, and writes one clip per episode in the format of
:mod:`world_model.data.clips`.
Clip names are derived from (scenario, seed), so a killed recording restarts where it stopped:
complete clips are skipped, a partial one is rewritten. The settings that shape a clip's content
(resolution, sensors, duration, randomization, action type, excluded categories) are kept in the
dataset's ``recording.json``; resuming into it with other settings is refused rather than mixed.

``workers`` > 1 records clips in that many processes (``m4world record --workers N``): the command's
own process and N - 1 spawned ones, which take the next clip whenever they are free. Every clip
depends on its own (scenario, seed) only, so the clips, their names and the dataset's recording
order (``dataset.json``, written by the parent in job order) are byte for byte the serial run's.
"""

from __future__ import annotations

import json
import os
import zlib
from collections.abc import Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from m4world_env.policies import IDMAutopilot, driving_style
from m4world_env.scenario import Scenario, list_scenarios, load_scenario, randomize_scenario
from m4world_env.traffic import TrafficBridge
from world_model.data import Clip, clip_exists, register_clip, write_clip
from world_model.data.clips import write_json_atomic
from world_model.raster.crops import ReferenceCrops
from world_model.scene import SceneFrame
from world_model.sensors import BevSpec, LidarSpec, default_rig
from world_model.sim import ProceduralSimulator

DEFAULT_STYLE = "steady"


@dataclass
class RecordConfig:
    """What to record. ``duration`` (s) overrides the scenarios' own when set."""

    scenarios: Sequence[str]
    episodes: int = 1
    out: Path = Path("data/clips")
    seed: int = 0
    randomize: bool = True
    duration: float | None = None
    height: int = 64
    width: int = 112
    lidar: LidarSpec = field(default_factory=LidarSpec)
    bev: BevSpec = field(default_factory=BevSpec)
    action_type: str = "discrete_meta"
    exclude_categories: tuple[
        str, ...
    ] = ()  # drop scripted objects of these categories (e.g. a base set without a rare case)
    # Ego driving styles (policies.DRIVING_STYLES), cycled over the episodes: episode seed s drives
    # with styles[s % len(styles)].
    styles: tuple[str, ...] = (DEFAULT_STYLE,)

    def __post_init__(self) -> None:
        if not self.styles:
            raise ValueError("RecordConfig.styles needs at least one driving style")
        for name in self.styles:
            driving_style(name)  # raises, naming the known styles

    def style(self, seed: int) -> str:
        """The driving style of the episode with ``seed``."""
        return self.styles[seed % len(self.styles)]


def exclude_categories(scenario: Scenario, categories: Sequence[str]) -> Scenario:
    """The scenario without any object of ``categories``: scripted objects dropped, and the IDM
    traffic mix without them (a base dataset for a rare case must never show it, §5)."""
    objects = [o for o in scenario.objects if o.category not in categories]
    mix = {c: w for c, w in scenario.traffic.mix.items() if c not in categories and w > 0} or {"car": 1.0}
    traffic = scenario.traffic.model_copy(update={"mix": mix})
    return scenario.model_copy(update={"objects": objects, "traffic": traffic})


def clip_name(scenario: str, seed: int) -> str:
    return f"{scenario}__s{seed:06d}"


SCENARIO_KEYS = 97  # scenario keys stay below this, so training seeds stay below 10^6 (evalset.py)


def scenario_key(name: str) -> int:
    """A stable small integer per scenario name, whatever the order scenarios are listed in: the
    bundled scenario's position among the bundled ones, else a hash of the name past them."""
    bundled = list_scenarios()
    if name in bundled:
        return bundled.index(name)
    return len(bundled) + zlib.crc32(name.encode()) % (SCENARIO_KEYS - len(bundled))


def episode_seed(base_seed: int, scenario_key: int, episode: int) -> int:
    """Distinct, stable seeds per (scenario, episode); independent of how many are recorded."""
    return base_seed * 1_000_003 + scenario_key * 10_007 + episode


class RecordingMismatchError(ValueError):
    """A dataset directory already holds clips recorded with other settings."""


RECORDING_MANIFEST = "recording.json"


def check_recording_settings(out: Path, settings: dict) -> None:
    """Write ``settings`` to ``out/recording.json``, or, when the directory was recorded before,
    refuse settings that differ from the recorded ones (clips of two resolutions must not mix)."""
    path = Path(out) / RECORDING_MANIFEST
    settings = json.loads(json.dumps(settings))  # tuples -> lists, as they come back from disk
    if path.exists():
        recorded = json.loads(path.read_text())
        changed = sorted(k for k in set(recorded) | set(settings) if recorded.get(k) != settings.get(k))
        if changed:
            diff = "; ".join(f"{k}: recorded {recorded.get(k)!r}, now {settings.get(k)!r}" for k in changed)
            raise RecordingMismatchError(
                f"{out} was recorded with other settings ({diff}); record into another --out or "
                "repeat the original settings to resume"
            )
        return
    Path(out).mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, settings)


def content_settings(cfg: RecordConfig) -> dict:
    """The settings of ``cfg`` that shape the clips' content (not which or how many are recorded)."""
    return {
        "randomize": cfg.randomize,
        "duration": cfg.duration,
        "height": cfg.height,
        "width": cfg.width,
        "lidar": asdict(cfg.lidar),
        "bev": asdict(cfg.bev),
        "action_type": cfg.action_type,
        "exclude_categories": sorted(cfg.exclude_categories),
        # Only a mix is written: datasets recorded before styles existed drove the default style.
        **({"styles": list(cfg.styles)} if cfg.styles != (DEFAULT_STYLE,) else {}),
    }


def drive_episode(scenario: Scenario, seed: int, cfg: RecordConfig) -> list[SceneFrame]:
    """The scene frames of one episode (traffic and ego, no sensors): the scenario randomized
    with ``seed`` when ``cfg.randomize``, the ego driven in the episode's style."""
    rng = np.random.default_rng(seed)
    if cfg.randomize:
        scenario = randomize_scenario(scenario, rng)
    if cfg.exclude_categories:
        scenario = exclude_categories(scenario, cfg.exclude_categories)
    if cfg.duration is not None:
        scenario = scenario.model_copy(update={"duration": cfg.duration})
    rig = default_rig(width=cfg.width, height=cfg.height)
    bridge = TrafficBridge(scenario, action_type=cfg.action_type, rig=rig, lidar=cfg.lidar, bev=cfg.bev)
    frames = [bridge.reset(seed=seed)]
    policy = IDMAutopilot(driving_style(cfg.style(seed)), seed=seed)
    while not (bridge.truncated or bridge.crashed):
        frames.extend(bridge.step(policy(bridge)))
    return frames


def record_episode(
    scenario: Scenario, seed: int, cfg: RecordConfig, sim: ProceduralSimulator | None = None
) -> tuple[list[SceneFrame], np.ndarray, np.ndarray, np.ndarray, ReferenceCrops]:
    """Run one episode and render every sensor frame. Returns frames, cameras, lidar, bev and the
    objects' reference crops (with the frame each was cut at)."""
    frames = drive_episode(scenario, seed, cfg)
    sim = sim or ProceduralSimulator()
    cams, lidars, bevs = [], [], []
    crops = ReferenceCrops(sim)  # the objects' "image descriptions", cut as the world-model env cuts them
    for fr in frames:
        obs = sim.render(fr, with_bev=True)
        cams.append(obs.cameras)
        lidars.append(obs.lidar)
        bevs.append(obs.bev)
        crops.update(fr, obs.cameras)
    return frames, np.stack(cams), np.stack(lidars), np.stack(bevs), crops


def record_clip(scenario: Scenario, seed: int, cfg: RecordConfig, sim: ProceduralSimulator | None = None) -> int:
    """Record and write one clip, leaving its registration in ``dataset.json`` to the caller.
    Returns its number of frames."""
    frames, cams, lidar, bev, crops = record_episode(scenario, seed, cfg, sim=sim)
    meta = {
        "seed": seed,
        "randomized": cfg.randomize,
        "base_scenario": scenario.name,
        "crop_since": crops.since,
        "ego_style": cfg.style(seed),
    }
    clip = Clip(clip_name(scenario.name, seed), frames, cams, lidar, bev, crops.crops, meta)
    write_clip(cfg.out, clip, register=False)
    return len(frames)


# Libraries' thread pools a worker process sizes at import: one thread each, the processes are the parallelism.
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


@contextmanager
def _single_threaded_children() -> Iterator[None]:
    """Worker processes started inside see one thread per library (the environment is read when
    their libraries load); this process's environment is restored after."""
    saved = {k: os.environ.get(k) for k in THREAD_VARIABLES}
    os.environ.update(dict.fromkeys(THREAD_VARIABLES, "1"))
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _init_worker() -> None:
    import cv2

    cv2.setNumThreads(1)
    try:
        import torch
    except ImportError:
        return
    torch.set_num_threads(1)


_worker_sim: ProceduralSimulator | None = None  # one simulator per worker process: its caches serve every clip


def _record_in_worker(job: tuple[Scenario, int, RecordConfig]) -> int:
    global _worker_sim
    _worker_sim = _worker_sim or ProceduralSimulator()
    return record_clip(*job, sim=_worker_sim)


# Clips queued per spawned worker: one to record and one waiting, so that a worker that finishes
# while this process records a clip of its own need not wait for it.
QUEUED_PER_WORKER = 2


def _record_beside_pool(
    todo: list[tuple[Scenario, int, RecordConfig]], pool: ProcessPoolExecutor, workers: int, sim: ProceduralSimulator
) -> Iterator[int]:
    """Frame counts of ``todo``'s clips in job order, recorded by the ``workers`` processes of
    ``pool`` and by this process, which records the next clip itself whenever every worker's queue
    is full (so the workers' start, a few seconds of imports, is spent recording too)."""
    results: dict[int, Future | int] = {}

    def ready(k: int) -> bool:
        r = results.get(k)
        return r is not None and (not isinstance(r, Future) or r.done())

    def take(k: int) -> int:
        r = results.pop(k)
        return r.result() if isinstance(r, Future) else r

    following, emitted = 0, 0
    with _single_threaded_self():
        while emitted < len(todo):
            queued = sum(isinstance(r, Future) and not r.done() for r in results.values())
            while following < len(todo) and queued < QUEUED_PER_WORKER * workers:
                results[following] = pool.submit(_record_in_worker, todo[following])
                following, queued = following + 1, queued + 1
            while emitted < len(todo) and ready(emitted):
                yield take(emitted)
                emitted += 1
            if following < len(todo):  # every worker's queue is full: record the next clip here
                results[following] = record_clip(*todo[following], sim=sim)
                following += 1
            elif emitted < len(todo):  # every clip handed out: wait for the next in order
                yield take(emitted)
                emitted += 1


@contextmanager
def _single_threaded_self() -> Iterator[None]:
    """OpenCV in this process on one thread while it records beside the workers (the processes
    are the parallelism); its thread count is restored after."""
    import cv2

    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def record(cfg: RecordConfig, progress: bool = True, workers: int = 1) -> list[str]:
    """Record ``episodes`` clips per scenario into ``cfg.out`` in ``workers`` processes; returns
    the clip names (existing included) in recording order."""
    from tqdm import tqdm

    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    scenarios = [load_scenario(s) for s in cfg.scenarios]
    seen = [sc.name for sc in scenarios]
    repeated = sorted({n for n in seen if seen.count(n) > 1})
    if repeated:
        raise ValueError(f"scenario name(s) {repeated} given more than once; clip names come from scenario names")
    check_recording_settings(cfg.out, content_settings(cfg))
    jobs = [(sc, episode_seed(cfg.seed, scenario_key(sc.name), e)) for sc in scenarios for e in range(cfg.episodes)]
    names = [clip_name(sc.name, seed) for sc, seed in jobs]
    todo = [(sc, seed, cfg) for (sc, seed), name in zip(jobs, names, strict=True) if not clip_exists(cfg.out, name)]
    sim = ProceduralSimulator()
    if workers == 1 or len(todo) < 2:
        frame_counts: Iterator[int] = (record_clip(*job, sim=sim) for job in todo)
        pool = None
    else:  # spawned, not forked: a fork would copy this process's thread pools (OpenCV's, torch's) locked
        with _single_threaded_children():
            spawned = min(workers, len(todo)) - 1
            pool = ProcessPoolExecutor(spawned, get_context("spawn"), _init_worker)
        frame_counts = _record_beside_pool(todo, pool, spawned, sim)
    bar = tqdm(total=len(jobs), desc="recording", unit="clip", disable=not progress)
    bar.update(len(jobs) - len(todo))
    try:
        # Registered in job order as each clip completes: dataset.json lists the serial run's order. A
        # clip written by a process killed before its registration is registered when resumed (below).
        for (sc, seed, _), frames in zip(todo, frame_counts, strict=True):
            register_clip(cfg.out, clip_name(sc.name, seed))
            bar.set_postfix_str(f"{clip_name(sc.name, seed)}: {frames} frames")
            bar.update()
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
        bar.close()
    for name in names:
        register_clip(cfg.out, name)  # resumed clips: listed already, unless written before a kill
    return names
