"""The agreement run's summary and its markdown report.

:func:`build_summary` turns the episode records of a zoo run (see :mod:`m4world_env.agreement.stats`)
into one JSON-ready dict; :func:`markdown_report` and :func:`~m4world_env.agreement.plot.scatter_plot`
render that dict, so a
report can be re-rendered from the written ``summary.json`` without running anything.

The summary's shape (every float a plain float; a statistic that is undefined, a correlation with a
constant side, is ``None`` rather than ``nan`` so ``json.dumps(summary, allow_nan=False)`` works)::

    {
      "checkpoint": str,                        # the world-model bundle the run used (or its stand-in)
      "scenarios": [str, ...],
      "seeds": [int, ...],
      "steps": int,                             # policy steps per episode
      "seconds": float,                         # wall time of the whole run
      "cell_seconds": float, "jobs": int,       # optional, added by the runner
      "metrics": ["pdms", "collision", "off_road", "progress", "ttc_violation"],
      "bootstrap": {"resamples": int, "level": float, "rng_seed": int},
      "policies": {                             # in name order
        name: {
          "family": str, "citation": str, "description": str, "episodes": int,
          metric: {"truth": float, "model": float,             # for every metric of "metrics":
                   "truth_ci": [low, high], "model_ci": [low, high]},   # mean, bootstrap interval
        },
      },
      "agreement": {                            # over the policies' mean PDMS, see stats.agreement
        "metric": "pdms", "pearson": float | None, "spearman": float | None,
        "kendall": float | None, "mmrv": float, "mean_abs_delta": float,
        "collision_agreement": float, "episodes": int, "policies": int,
      },
      "agreement_ci": {statistic: [low, high] | None},  # stats.agreement_intervals, over episodes
      "by_scenario": {scenario: <same shape as "agreement">},  # in name order
      "disagreements": [                        # the largest |model - truth| PDMS first
        {"key": "policy/scenario/seed", "policy": str, "scenario": str, "seed": int,
         "truth_pdms": float, "model_pdms": float, "delta": float},   # delta = model - truth
      ],
      "videos": {key: relative path},           # optional, added by the runner: a disagreement's
    }                                           # side-by-side video, linked from the report
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from m4world_env.agreement.stats import (
    DEFAULT_LEVEL,
    DEFAULT_RESAMPLES,
    METRICS,
    Record,
    agreement,
    agreement_by_scenario,
    agreement_intervals,
    episode_key,
    most_disagreeing,
    policy_scores,
)

SECONDS_PER_MINUTE = 60.0
DEFAULT_TOP_K = 6


@dataclass(frozen=True)
class PublishedReference:
    """Another system's published agreement between its simulator and its ground truth."""

    system: str
    setting: str
    pearson: float | None
    mmrv: float | None
    policies: int | None


# Other systems' published figures, on their own policies, tasks and scores: a scale for reading ours,
# not a measurement of this world model.
PUBLISHED_REFERENCES: tuple[PublishedReference, ...] = (
    PublishedReference("NAVSIM v2 pseudo-simulation", "driving planners' scores", 0.89, None, 83),
    PublishedReference("WorldEval", "robot policies, world model vs real robot", 0.942, 0.044, None),
    PublishedReference("SIMPLER", "robot policies, simulator vs real robot", 0.924, None, None),
)

# Rates of 0/1 flags over a few episodes are coarse: two decimals; PDMS, progress and the
# correlations are continuous: three.
SCORE_DECIMALS = 3
RATE_DECIMALS = 2
# The per-policy table's rate columns: (metric, header, decimals).
RATE_COLUMNS = (("collision", "collision", RATE_DECIMALS), ("off_road", "off-road", RATE_DECIMALS))


def _plain(value: float) -> float | None:
    """A JSON-safe float: ``None`` for nan."""
    value = float(value)
    return None if math.isnan(value) else value


def _plain_agreement(stats: Mapping[str, Any]) -> dict[str, Any]:
    return {k: _plain(v) if isinstance(v, float) else v for k, v in stats.items()}


@dataclass(frozen=True)
class RunHeader:
    """What a zoo run was, the head of its summary: the world-model bundle, the scenarios and seeds
    it ran, the policy steps per episode and its wall time."""

    checkpoint: str
    scenarios: Sequence[str]
    seeds: Sequence[int]
    steps: int
    seconds: float


def build_summary(
    records: Iterable[Record],
    run: RunHeader,
    *,
    members: Mapping[str, Mapping[str, str]],
    rng_seed: int = 0,
    top_k: int = DEFAULT_TOP_K,
) -> dict[str, Any]:
    """The run's summary (the shape is in this module's docstring) from its episode records.

    ``members`` maps each policy name to its ``{"family", "citation", "description"}``; every policy
    of the records must have one (a member that ran no episode is left out). Records of a scenario or
    seed that ``scenarios`` / ``seeds`` do not list are an error: the report's header would not
    describe them."""
    records = list(records)
    scenarios, seeds = run.scenarios, run.seeds
    unlisted = sorted(
        {(str(r["scenario"]), int(r["seed"])) for r in records} - {(s, int(seed)) for s in scenarios for seed in seeds}
    )
    if unlisted:
        raise ValueError(f"records of scenarios/seeds the run does not list: {unlisted[:5]}")
    scores = {metric: policy_scores(records, metric, rng_seed=rng_seed) for metric in METRICS}
    missing = sorted(set(scores["pdms"]) - set(members))
    if missing:
        raise ValueError(f"no member description (family, citation, description) for policies {missing}")
    policies: dict[str, dict[str, Any]] = {}
    for name in sorted(scores["pdms"]):
        member = members[name]
        entry: dict[str, Any] = {
            "family": str(member["family"]),
            "citation": str(member["citation"]),
            "description": str(member.get("description", "")),
            "episodes": scores["pdms"][name]["episodes"],
        }
        for metric in METRICS:
            s = scores[metric][name]
            entry[metric] = {
                "truth": s["truth"],
                "model": s["model"],
                "truth_ci": list(s["truth_ci"]),
                "model_ci": list(s["model_ci"]),
            }
        policies[name] = entry
    disagreements = [
        {
            "key": episode_key(policy, scenario, seed),
            "policy": policy,
            "scenario": scenario,
            "seed": seed,
            "truth_pdms": truth,
            "model_pdms": model,
            "delta": model - truth,
        }
        for policy, scenario, seed, truth, model in most_disagreeing(records, top_k)
    ]
    return {
        "checkpoint": str(run.checkpoint),
        "scenarios": [str(s) for s in scenarios],
        "seeds": [int(s) for s in seeds],
        "steps": int(run.steps),
        "seconds": float(run.seconds),
        "metrics": list(METRICS),
        "bootstrap": {"resamples": DEFAULT_RESAMPLES, "level": DEFAULT_LEVEL, "rng_seed": int(rng_seed)},
        "policies": policies,
        "agreement": _plain_agreement(agreement(records)),
        "agreement_ci": {
            name: None if math.isnan(low) else [low, high]
            for name, (low, high) in agreement_intervals(records, rng_seed=rng_seed).items()
        },
        "by_scenario": {name: _plain_agreement(a) for name, a in agreement_by_scenario(records).items()},
        "disagreements": disagreements,
    }


def number(value: float | None, decimals: int = SCORE_DECIMALS) -> str:
    """A number for a table; "n/a" for an undefined statistic."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    return f"{value:.{decimals}f}"


def _signed(value: float, decimals: int = SCORE_DECIMALS) -> str:
    return f"{value:+.{decimals}f}".replace("-", "−")


def _cell(text: object) -> str:
    """Text for a markdown table cell: a "|" would end the cell."""
    return str(text).replace("|", "\\|")


def _table(header: Sequence[str], rows: Iterable[Sequence[object]]) -> list[str]:
    lines = ["| " + " | ".join(_cell(h) for h in header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]
    return lines


def _with_ci(entry: Mapping[str, Any], side: str) -> str:
    low, high = entry[f"{side}_ci"]
    return f"{number(entry[side])} [{number(low)}, {number(high)}]"


def _pair(entry: Mapping[str, Any], decimals: int) -> str:
    return f"{number(entry['truth'], decimals)} / {number(entry['model'], decimals)}"


def level_percent(summary: Mapping[str, Any]) -> str:
    level = summary.get("bootstrap", {}).get("level", DEFAULT_LEVEL)
    return f"{level * 100:g}%"


def _headline(summary: Mapping[str, Any]) -> list[str]:
    a = summary["agreement"]
    refs = PUBLISHED_REFERENCES
    dash = "–"

    def ref_row(label: str, ours: str, field: str) -> list[str]:
        """A statistic of ours next to the references' published values of ``field``."""
        values = [getattr(r, field) for r in refs]
        return [label, ours, *(dash if v is None else f"{v:g}" for v in values)]

    intervals = summary.get("agreement_ci", {})

    def ours(statistic: str) -> str:
        """The run's value and, where the summary has it, its bootstrap interval."""
        interval = intervals.get(statistic)
        bounds = "" if interval is None else f" [{number(interval[0])}, {number(interval[1])}]"
        return number(a[statistic]) + bounds

    rows = [
        ref_row("Pearson r ↑", ours("pearson"), "pearson"),
        ["Spearman ρ ↑", ours("spearman"), *(dash for _ in refs)],
        ["Kendall τ ↑", ours("kendall"), *(dash for _ in refs)],
        ref_row("MMRV ↓", ours("mmrv"), "mmrv"),
        ["mean |ΔPDMS| ↓", ours("mean_abs_delta"), *(dash for _ in refs)],
        ["collision agreement (episodes) ↑", ours("collision_agreement"), *(dash for _ in refs)],
        ref_row("policies", str(a["policies"]), "policies"),
        ["episodes (paired)", str(a["episodes"]), *(dash for _ in refs)],
    ]
    header = ["statistic", "**this run**", *(f"{r.system} †" for r in refs)]
    lines = ["## Agreement over the zoo", ""]
    lines.append(
        f"Over the {a['policies']} policies' mean {a['metric'].upper()}: the world model's scores "
        "against the ground truth's (the procedural renderer)."
        + (
            f" In brackets, {level_percent(summary)} bootstrap intervals (BCa) with the episodes, "
            "(scenario, seed) pairs, resampled: how much the statistic could move with other seeds."
            if intervals
            else ""
        )
    )
    lines += ["", *_table(header, rows), ""]
    settings = "; ".join(f"{r.system}: {r.setting}" for r in refs)
    lines.append(
        "† Published figures of other systems, measured on their own policies, tasks and scores "
        f"({settings}). They are not measurements of this world model; they show the scale the field "
        "reads such numbers on."
    )
    return lines


def _policy_table(summary: Mapping[str, Any]) -> list[str]:
    level = level_percent(summary)
    ranked = sorted(summary["policies"].items(), key=lambda item: (-item[1]["pdms"]["truth"], item[0]))
    header = [
        "policy",
        "family",
        f"truth PDMS [{level} CI]",
        f"world-model PDMS [{level} CI]",
        "Δ",
        *(f"{title} T / M" for _, title, _ in RATE_COLUMNS),
        "progress T / M",
        "TTC violations T / M",
    ]
    rows = []
    for name, p in ranked:
        rows.append(
            [
                f"`{name}`",
                p["family"],
                _with_ci(p["pdms"], "truth"),
                _with_ci(p["pdms"], "model"),
                _signed(p["pdms"]["model"] - p["pdms"]["truth"]),
                *(_pair(p[metric], decimals) for metric, _, decimals in RATE_COLUMNS),
                _pair(p["progress"], SCORE_DECIMALS),
                _pair(p["ttc_violation"], RATE_DECIMALS),
            ]
        )
    return [
        "## Policies",
        "",
        "Sorted by ground-truth PDMS. T = ground truth, M = world model; collision, off-road and TTC "
        "violations are the share of episodes with the event; Δ = world model − truth.",
        "",
        *_table(header, rows),
    ]


def _scenario_table(summary: Mapping[str, Any]) -> list[str]:
    header = [
        "scenario",
        "policies",
        "episodes",
        "Pearson r",
        "Spearman ρ",
        "Kendall τ",
        "MMRV",
        "mean |ΔPDMS|",
        "collision agreement",
    ]
    rows = [
        [
            f"`{name}`",
            a["policies"],
            a["episodes"],
            number(a["pearson"]),
            number(a["spearman"]),
            number(a["kendall"]),
            number(a["mmrv"]),
            number(a["mean_abs_delta"]),
            number(a["collision_agreement"]),
        ]
        for name, a in summary["by_scenario"].items()
    ]
    return ["## Per scenario", "", *_table(header, rows)]


def _disagreements(summary: Mapping[str, Any]) -> list[str]:
    videos = summary.get("videos") or {}
    lines = ["## Most disagreeing episodes", ""]
    if not summary["disagreements"]:
        return [*lines, "No episodes."]
    for i, d in enumerate(summary["disagreements"], start=1):
        video = videos.get(d["key"])
        link = f" — [video]({video})" if video else ""
        lines.append(
            f"{i}. `{d['policy']}` on `{d['scenario']}`, seed {d['seed']}: truth PDMS "
            f"{number(d['truth_pdms'])}, world model {number(d['model_pdms'])} "
            f"(Δ {_signed(d['delta'])}){link}"
        )
    return lines


def _members(summary: Mapping[str, Any]) -> list[str]:
    lines = ["## Zoo", ""]
    for p in summary["policies"].values():
        description = f": {p['description']}" if p.get("description") else ""
        lines.append(f"- `{p['citation']}` ({p['family']}){description}")
    return lines


def _jobs_note(summary: Mapping[str, Any]) -> str:
    """How the run's wall time was spent, where the runner recorded it."""
    if "jobs" not in summary or "cell_seconds" not in summary:
        return ""
    return (
        f" of wall time, videos included, with {summary['jobs']} cell(s) at a time "
        f"(the cells' own times add up to {summary['cell_seconds'] / SECONDS_PER_MINUTE:.1f} min)"
    )


def markdown_report(summary: Mapping[str, Any]) -> str:
    """The run's report as markdown: the zoo-level agreement next to the field's published figures,
    the per-policy table (by ground-truth PDMS, descending), the per-scenario agreement, the most
    disagreeing episodes (linked to ``summary["videos"][key]`` where there is one), the zoo's
    members and the run's time. ``summary`` has :func:`build_summary`'s shape (module docstring)."""
    scenarios, seeds = summary["scenarios"], summary["seeds"]
    minutes = summary["seconds"] / SECONDS_PER_MINUTE
    lines = [
        "# World model vs ground truth over a policy zoo",
        "",
        f"- checkpoint: `{summary['checkpoint']}`",
        f"- {len(summary['policies'])} policies × {len(scenarios)} scenarios × {len(seeds)} seeds "
        f"(seeds {', '.join(str(s) for s in seeds)}), {summary['steps']} steps per episode",
        f"- run time: {minutes:.1f} min{_jobs_note(summary)}",
        "",
        *_headline(summary),
        "",
        *_policy_table(summary),
        "",
        *_scenario_table(summary),
        "",
        *_disagreements(summary),
        "",
        *_members(summary),
        "",
    ]
    return "\n".join(lines)
