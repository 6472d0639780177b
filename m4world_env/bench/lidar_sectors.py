"""What a LiDAR-reading policy reads on the world model vs the ground truth, on the same states.

    m4world bench lidar_sectors --out F.json [--scenarios highway_sunny_day merge_cut_in ...] \
        [--seeds 0 1] [--steps 40] [--checkpoint BUNDLE]

For each scenario and seed, one episode: the built-in ``lane_keeping`` policy drives
``backend="procedural"`` (the ground truth) and its very actions are fed to ``backend="world_model"``
(LiDAR only: no camera decoded), both reset with the seed, so the traffic is the same on both. After
each step the two range maps are read like the evaluation's "What a policy reads"
(:func:`world_model.eval.decisions.lidar_decisions`, with the world-model env's LidarSpec): per
30-degree azimuth sector and beam band, the nearest return that is not the road. A sector whose
ground truth has one within ``OBJECT_RANGE_M`` holds an object. An episode stops when either env
ends.

Per scenario (its seeds pooled) and over all of them, per beam band: ``objects``, the median
absolute range error of the objects the world model also reports (``median_error_m``),
``farther_or_missed`` (its return more than ``FAR_ERROR_M`` farther, or none), ``missed``, and
``phantom`` (of the sectors without an object, those where it reports one within range and more
than ``FAR_ERROR_M`` nearer than the ground truth); and of the objects within ``CLOSE_RANGE_M``
(``close_objects``: a car alongside, one cutting in), ``close_off``: those the world model misses or
reads more than ``CLOSE_ERROR_M`` off, where a policy that keeps a corridor clear decides by tenths
of a metre. A markdown table is printed; the JSON holds the figures and the run's settings.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable

import numpy as np

from m4world_env.same_states import model_env_kwargs, replay_main, replay_settings, replayed_steps
from world_model.eval.decisions import (
    BEAM_BANDS,
    CLOSE_ERROR_M,
    CLOSE_RANGE_M,
    FAR_ERROR_M,
    OBJECT_RANGE_M,
    P50,
    DecisionSums,
    lidar_decisions,
    percentile,
    share,
)
from world_model.sensors import LidarSpec

DEFAULT_SCENARIOS = (
    "highway_sunny_day",
    "two_way_overtake_dusk",
    "roundabout_fog",
    "merge_cut_in",
    "highway_dense_rain_dusk",
    "intersection_pedestrian_night",
)
ALL = "all scenarios"  # the row pooled over every scenario
COLUMNS = ("objects", "median_error_m", "farther_or_missed", "missed", "phantom", "close_objects", "close_off")


def world_model_kwargs(checkpoint: str | None) -> dict:
    """gym.make keywords of the world-model env: LiDAR only, ``checkpoint`` where given."""
    return model_env_kwargs(("lidar",), checkpoint)


def compare(truths: Iterable[np.ndarray], models: Iterable[np.ndarray], spec: LidarSpec) -> DecisionSums:
    """The sector readings of paired range maps (beams, azimuth) m, summed over the pairs:
    ``truths`` the ground truth's, ``models`` the world model's, step by step."""
    return sum(
        (lidar_decisions(t, m, spec) for t, m in zip(truths, models, strict=True)),
        DecisionSums(),
    )


def episode(scenario: str, seed: int, steps: int, model: dict) -> tuple[list[np.ndarray], list[np.ndarray], LidarSpec]:
    """Up to ``steps`` policy steps of ``scenario``: the ground truth's range maps after each step,
    the ``model`` env's (gym.make keywords) fed the same actions, and the model env's LidarSpec."""
    truths, models, spec = [], [], None
    for step in replayed_steps(scenario, seed, steps, model):
        truths.append(step.truth_obs["lidar"])
        models.append(step.model_obs["lidar"])
        spec = step.model.lidar_spec
    return truths, models, spec


def figures(sums: DecisionSums) -> dict[str, dict]:
    """Per beam band: the objects, the median |range error| (m) of those seen, and the shares
    farther-or-missed and missed (of the objects) and phantom (of the empty sectors)."""
    out = {}
    for band in BEAM_BANDS:
        s = sums.sectors.get(band.name)
        if s is None:
            raise ValueError(f"no readings of beam band {band.name!r}")
        out[band.name] = {
            "objects": s.objects,
            "median_error_m": percentile(s.errors_m, P50),
            "farther_or_missed": share(s.farther + s.missed, s.objects),
            "missed": share(s.missed, s.objects),
            "phantom": share(s.phantom, s.empty),
            "empty": s.empty,
            "close_objects": s.close,
            "close_off": share(s.close_off, s.close),
        }
    return out


def table(results: dict[str, dict[str, dict]]) -> str:
    """A markdown table of :func:`figures` per row name (scenario, or all of them) and band."""
    head = ["scenario", "band", "objects", "median error (m)", "farther or missed", "missed", "phantom"]
    head += [f"within {CLOSE_RANGE_M:g} m", f"of those off > {CLOSE_ERROR_M:g} m"]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for name, bands in results.items():
        for band, f in bands.items():
            cells = [name, band, str(f["objects"]), *(_cell(f[k]) for k in COLUMNS[1:5])]
            cells += [str(f["close_objects"]), _cell(f["close_off"])]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _cell(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}" if value >= 1 else f"{value:.3f}"


def run(scenarios: list[str], seeds: list[int], steps: int, checkpoint: str | None) -> dict:
    """Every episode; the figures per scenario (seeds pooled) and over all of them, with the settings."""
    model = world_model_kwargs(checkpoint)
    per_scenario: dict[str, DecisionSums] = {}
    steps_run: dict[str, dict[str, int]] = {}
    for scenario in scenarios:
        per_scenario[scenario], steps_run[scenario] = DecisionSums(), {}
        for s in seeds:
            truths, models, spec = episode(scenario, s, steps, model)
            per_scenario[scenario] += compare(truths, models, spec)
            steps_run[scenario][str(s)] = len(truths)
            print(f"{scenario} seed {s}: {len(truths)} steps", file=sys.stderr, flush=True)
    pooled = sum(per_scenario.values(), DecisionSums())
    results = {name: figures(sums) for name, sums in per_scenario.items()}
    return {
        **replay_settings(scenarios, seeds, steps, checkpoint),
        "object_range_m": OBJECT_RANGE_M,
        "far_error_m": FAR_ERROR_M,
        "close_range_m": CLOSE_RANGE_M,
        "close_error_m": CLOSE_ERROR_M,
        "steps_run": steps_run,
        "results": {**results, ALL: figures(pooled)},
    }


def main(argv: list[str] | None = None) -> int:
    return replay_main("m4world bench lidar_sectors", __doc__, (DEFAULT_SCENARIOS, (0, 1), 40), run, table, argv)


if __name__ == "__main__":
    sys.exit(main())
