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
"""

from __future__ import annotations

import json
import zlib
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from m4world_env.policies import IDMAutopilot, driving_style
from m4world_env.scenario import Scenario, list_scenarios, load_scenario, randomize_scenario
from m4world_env.traffic import TrafficBridge
from world_model.data import clip_exists, write_clip
from world_model.data.clips import write_json_atomic
from world_model.scene import SceneFrame
from world_model.sensors import BevSpec, LidarSpec, default_rig
from world_model.sim import ProceduralSimulator
from world_model.sim.reference_crops import ReferenceCrops

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


def record(cfg: RecordConfig, progress: bool = True) -> list[str]:
    """Record ``episodes`` clips per scenario into ``cfg.out``; returns the clip names (existing included)."""
    from tqdm import tqdm

    scenarios = [load_scenario(s) for s in cfg.scenarios]
    seen = [sc.name for sc in scenarios]
    repeated = sorted({n for n in seen if seen.count(n) > 1})
    if repeated:
        raise ValueError(f"scenario name(s) {repeated} given more than once; clip names come from scenario names")
    check_recording_settings(cfg.out, content_settings(cfg))
    jobs = [(sc, episode_seed(cfg.seed, scenario_key(sc.name), e)) for sc in scenarios for e in range(cfg.episodes)]
    names = []
    sim = ProceduralSimulator()
    bar = tqdm(jobs, desc="recording", unit="clip", disable=not progress)
    for sc, seed in bar:
        name = clip_name(sc.name, seed)
        names.append(name)
        if clip_exists(cfg.out, name):
            bar.set_postfix_str(f"skip {name}")
            continue
        frames, cams, lidar, bev, crops = record_episode(sc, seed, cfg, sim=sim)
        write_clip(
            cfg.out,
            name,
            frames,
            cams,
            lidar,
            bev,
            crops=crops.crops,
            extra_meta={
                "seed": seed,
                "randomized": cfg.randomize,
                "base_scenario": sc.name,
                "crop_since": crops.since,
                "ego_style": cfg.style(seed),
            },
        )
        bar.set_postfix_str(f"{name}: {len(frames)} frames")
    return names
