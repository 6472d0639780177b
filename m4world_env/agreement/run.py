"""The agreement run: every zoo policy on both backends over the same scenarios and seeds.

    m4world agreement --out out/agreement              # 3 scenarios x 2 seeds
    m4world agreement --full --out out/agreement_full  # 6 scenarios x 4 seeds
    m4world agreement --checkpoint MY_BUNDLE --out out/agreement_mine
    m4world agreement --truth-noise 2 --out out/agreement_floor  # the ground truth against itself
    m4world agreement --dtype float32 --out out/agreement_fp32  # the DiTs in float32 on any machine

The work is cut into cells, one per (backend, scenario, seed). A cell runs every policy at once in
one vector env (one row per policy, one batched world-model call per step): every row starts from
the same first frame (the same scene and seed), sampled once, and a row whose episode has ended
idles until the cell is done. Each cell's episodes are written to ``OUT/episodes/`` as it finishes,
so a run that is stopped resumes where it was (``OUT/plan.json`` guards against resuming with other
settings); ``OUT/progress.json`` tells how far it is. At the end: ``summary.json``, ``report.md``,
``scatter.png`` and, for the episodes the backends disagree on most, side-by-side videos
(ground truth | world model, the policy's action and the score so far) in ``videos/``.

A row's episode is exactly ``m4world eval --policy P --scenarios S --seed SEED --backend B
--max-steps STEPS``'s (the vector env equals single envs bit for bit on CPU, and the policy's seed is
drawn the same way). A run's wall time and its cells' own times are in its report.

With ``truth_noise`` (``--truth-noise SIGMA``) the world model's place is taken by the ground truth
whose cameras the policies see through Gaussian noise of SIGMA grey levels (:func:`noisy_cameras`),
the LiDAR as it is: two ground truths no policy should tell apart. How far their scores still fall
apart, with this zoo, these scenarios and seeds, is what no world model can be asked to beat.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from m4world_env.agreement import (
    DEFAULT_SCENARIOS,
    DEFAULT_SEEDS,
    DEFAULT_STEPS,
    DEFAULT_VIDEOS,
    FULL_SCENARIOS,
    FULL_SEEDS,
    FULL_STEPS,
)
from m4world_env.agreement.plot import scatter_plot
from m4world_env.agreement.render import DEFAULT_TOP_K, RunHeader, build_summary, markdown_report
from m4world_env.zoo.base import SENSOR_KEYS
from world_model.bundle import load_bundle_files, resolve_bundle
from world_model.precision import check_dtype

BACKEND_PAIR = ("procedural", "world_model")
PROGRESS_SECONDS = 10.0  # how often progress.json is rewritten while cells run in other processes
PARENT_POLL_SECONDS = 2.0  # how often a cell worker checks that the run's process is still there
SHIPPED_CHECKPOINT = "shipped"  # how a plan names the bundle that comes with the package
TRUTH_NOISE_MAX = 64.0  # grey levels: beyond this the cameras are mostly noise


@dataclass(frozen=True)
class AgreementPlan:
    """What a run covers. ``checkpoint``: a bundle path, or None for the shipped one.
    ``truth_noise``: None, the world model; else the ground truth seen through camera noise of that
    many grey levels in its place (module docstring). ``dtype``: the world model's DiTs' precision,
    the env's ``config.model.dtype`` ("auto": as the machine's hardware chooses)."""

    policies: tuple[str, ...]
    scenarios: tuple[str, ...]
    seeds: tuple[int, ...]
    steps: int
    checkpoint: str | None = None
    truth_noise: float | None = None
    dtype: str = "auto"

    def __post_init__(self) -> None:
        if not self.policies or not self.scenarios or not self.seeds:
            raise ValueError("an agreement run needs at least one policy, scenario and seed")
        for flag, values in (("--policies", self.policies), ("--scenarios", self.scenarios), ("--seeds", self.seeds)):
            if len(set(values)) != len(values):
                raise ValueError(f"{flag}: {list(values)} names one twice; each runs once")
        for name in self.scenarios:
            if Path(name).name != name or name.endswith((".yaml", ".yml")):
                raise ValueError(f"--scenarios {name}: give a bundled scenario's name (m4world scenarios lists them)")
        if isinstance(self.steps, bool) or not isinstance(self.steps, int) or self.steps < 1:
            raise ValueError(f"--steps must be a positive integer, got {self.steps!r}")
        noise = self.truth_noise
        if noise is not None and (
            isinstance(noise, bool) or not isinstance(noise, int | float) or not 0 < noise <= TRUTH_NOISE_MAX
        ):
            raise ValueError(f"--truth-noise must be grey levels in (0, {TRUTH_NOISE_MAX:g}], got {noise!r}")
        try:
            check_dtype(self.dtype)
        except ValueError as e:  # named as the command line's flag, as the checks above
            raise ValueError(f"--{e}") from None

    def to_json(self) -> dict[str, Any]:
        """The plan as ``plan.json`` keeps it: with each member's citation and the digests of its
        weight files and of the bundle's manifest, so a run never resumes with other drivers or
        another model under the same names."""
        from m4world_env import zoo

        d = {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}
        d["checkpoint"] = bundle_name(self.checkpoint)
        members = [zoo.member(p) for p in self.policies]
        d["citations"] = [m.citation for m in members]
        d["member_files"] = {m.name: [_digest(f) for f in m.files] for m in members if m.files}
        d["checkpoint_manifest"] = _digest(resolve_bundle(self.checkpoint) / "manifest.json")
        for key, default in (("truth_noise", None), ("dtype", "auto")):
            if d[key] == default:  # defaults left out: a default run keeps the plan.json it resumes from
                del d[key]
        return d

    @property
    def model_side(self) -> str:
        """What the report compares with the ground truth: the bundle, or the noisy ground truth."""
        if self.truth_noise is None:
            name = bundle_name(self.checkpoint)
            return name if self.dtype == "auto" else f"{name} ({self.dtype})"
        return f"the ground truth, its cameras seen through noise of {self.truth_noise:g} grey levels"


def bundle_name(checkpoint: str | None) -> str:
    """How a plan names its bundle: :data:`SHIPPED_CHECKPOINT`, or the bundle's absolute path."""
    return SHIPPED_CHECKPOINT if checkpoint is None else str(Path(checkpoint).resolve())


def _digest(path: Path) -> str:
    """The SHA-256 of a file's bytes (a missing file: "missing")."""
    path = Path(path)
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else "missing"


@dataclass(frozen=True)
class Cell:
    backend: str
    scenario: str
    seed: int

    def path(self, out: Path) -> Path:
        return out / "episodes" / self.backend / self.scenario / f"seed{self.seed}.json"

    def step_path(self, out: Path) -> Path:
        """Where a running cell keeps the step it has reached."""
        return out / "running" / f"{self.backend}__{self.scenario}__seed{self.seed}.json"


def cells(plan: AgreementPlan) -> list[Cell]:
    """The run's cells: each scenario and seed on the ground truth, then on the world model."""
    return [Cell(b, s, seed) for s in plan.scenarios for seed in plan.seeds for b in BACKEND_PAIR]


FILE_MODE = 0o644  # the run's files are for anyone who reads the report


def _write_text(path: Path, text: str) -> None:
    """``text`` to ``path`` atomically (a stopped run never leaves half a file)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.chmod(tmp, FILE_MODE)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _write_json(path: Path, data: Any) -> None:
    _write_text(path, json.dumps(data, indent=1))


def _check_plan(plan: AgreementPlan, out: Path) -> None:
    """Start a run in ``out``, or resume it when its plan is this one."""
    path = out / "plan.json"
    wanted = plan.to_json()
    if path.exists():
        found = json.loads(path.read_text())
        if found != wanted:
            changed = sorted(k for k in wanted if found.get(k) != wanted[k])
            raise ValueError(
                f"{out} holds a run with other settings ({', '.join(changed)} differ): resume it with the same "
                "options, or give another --out"
            )
    else:
        _write_json(path, wanted)


def run_cell(
    cell: Cell,
    plan: AgreementPlan,
    on_step: Callable[[int], None] | None = None,
    rollout_threads: int | None = None,
) -> list[dict[str, Any]]:
    """Every policy of ``plan`` for one episode of ``cell``'s scenario and seed on its backend, in one
    vector env; returns one record per policy (its ``episode_metrics`` and who, where, what).
    ``on_step(t)`` is called after each step ``t`` (1, 2, ...). ``rollout_threads``: the world
    model's ``config.model.rollout_threads`` (None: the env's default, a group per core)."""
    from m4world_env import zoo
    from m4world_env.evaluate import episode_policy_seed
    from m4world_env.vector import M4WorldVectorEnv

    members = [zoo.member(name) for name in plan.policies]
    n = len(members)
    noise = plan.truth_noise if cell.backend == "world_model" else None
    backend = cell.backend if noise is None else "procedural"
    venv = M4WorldVectorEnv(
        num_envs=n,
        scenario=cell.scenario,
        backend=backend,
        checkpoint=plan.checkpoint if backend == "world_model" else None,
        config={
            "observation_keys": list(SENSOR_KEYS),
            "model": {"rollout_threads": rollout_threads, "dtype": plan.dtype},
        },
    )

    def seen(row: dict[str, np.ndarray], i: int, t: int) -> dict[str, np.ndarray]:
        """Row ``i``'s observation after step ``t`` as its policy sees it."""
        return row if noise is None else noisy_cameras(row, noise, np.random.default_rng((cell.seed, i, t)))

    try:
        obs, infos = venv.reset(seed=[cell.seed] * n)
        geometry = zoo.SensorGeometry.of_env(venv.envs[0])
        drivers = [m.build(geometry, episode_policy_seed(env)) for m, env in zip(members, venv.envs, strict=True)]
        rows_obs = [seen({k: obs[k][i] for k in obs}, i, 0) for i in range(n)]
        rows_info: list[dict[str, Any]] = [{"speed": float(infos["speed"][i])} for i in range(n)]
        active = [True] * n
        steps = [0] * n
        for t in range(plan.steps):
            chunks = [
                env.advance(drivers[i](rows_obs[i], rows_info[i])) if active[i] else None
                for i, env in enumerate(venv.envs)
            ]
            observations = venv.backend.step(chunks)
            for i, env in enumerate(venv.envs):
                if not active[i]:
                    continue
                row, _reward, terminated, truncated, rows_info[i] = env.finish_step(chunks[i], observations[i])
                rows_obs[i] = seen(row, i, t + 1)
                steps[i] = t + 1
                active[i] = not (terminated or truncated)
            if on_step is not None:
                on_step(t + 1)
            if not any(active):
                break
    finally:
        venv.close()
    return [
        {
            "policy": m.name,
            "family": m.family,
            "citation": m.citation,
            "scenario": cell.scenario,
            "seed": cell.seed,
            "backend": cell.backend,
            "policy_steps": steps[i],
            **{k: float(v) for k, v in info["episode_metrics"].items()},
        }
        for i, (m, info) in enumerate(zip(members, rows_info, strict=True))
    ]


def noisy_cameras(obs: dict[str, np.ndarray], sigma: float, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """An observation dict with its ``"cameras"`` (uint8) seen through Gaussian noise of ``sigma``
    grey levels, rounded and clipped to 0..255; the other sensors as they are."""
    cameras = obs["cameras"].astype(np.float32) + rng.normal(0.0, sigma, obs["cameras"].shape).astype(np.float32)
    return {**obs, "cameras": np.clip(np.rint(cameras), 0, 255).astype(np.uint8)}


class Progress:
    """``OUT/progress.json``: cells done and running, the cells' seconds so far and an estimate of
    the rest (from the world-model and ground-truth cells' mean times so far, over the jobs)."""

    def __init__(self, out: Path, plan: AgreementPlan, total: list[Cell], jobs: int) -> None:
        self.path, self.plan, self.total, self.jobs = out / "progress.json", plan, total, jobs
        # Wall time of the run's earlier invocations (a resumed run adds to it).
        earlier = json.loads(self.path.read_text()) if self.path.exists() else {}
        self.earlier_wall = float(earlier.get("wall_seconds", 0.0))
        self.started = time.perf_counter()

    def _step(self, cell: Cell) -> int:
        path = cell.step_path(self.path.parent)
        try:
            return int(json.loads(path.read_text())["step"])
        except (OSError, ValueError, KeyError):  # not started, or between two writes
            return 0

    @property
    def wall_seconds(self) -> float:
        return self.earlier_wall + time.perf_counter() - self.started

    def update(self, done: list[dict[str, Any]], running: list[Cell]) -> None:
        seconds = {b: [c["seconds"] for c in done if c["backend"] == b] for b in BACKEND_PAIR}
        left = {b: sum(c.backend == b for c in self.total) - len(seconds[b]) for b in BACKEND_PAIR}
        eta = sum(left[b] * float(np.mean(seconds[b])) for b in BACKEND_PAIR if seconds[b]) / self.jobs
        estimated = all(seconds[b] or not left[b] for b in BACKEND_PAIR)
        _write_json(
            self.path,
            {
                "cells_done": len(done),
                "cells": len(self.total),
                "running": [{**asdict(c), "step": self._step(c), "steps": self.plan.steps} for c in running],
                "cell_seconds": sum(sum(s) for s in seconds.values()),
                "wall_seconds": self.wall_seconds,
                "seconds_left_estimate": eta if estimated else None,
            },
        )


def exit_with_parent(parent: int) -> None:
    """A cell worker's initializer: a daemon thread ends the worker once ``parent``, the run's
    process, is gone (killed, say, at the end of a session), so that no orphan goes on computing cells
    and holding a world model's memory. The cells already written stay; the next run resumes."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_POLL_SECONDS)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def timed_cell(cell: Cell, plan: AgreementPlan, out: Path, rollout_threads: int | None = None) -> dict[str, Any]:
    """Run ``cell`` and write its result (records and seconds) to its file; returns the result."""
    started = time.perf_counter()
    records = run_cell(cell, plan, lambda t: _write_json(cell.step_path(out), {"step": t}), rollout_threads)
    result = {**asdict(cell), "seconds": time.perf_counter() - started, "records": records}
    _write_json(cell.path(out), result)
    cell.step_path(out).unlink(missing_ok=True)
    return result


def run_agreement(
    plan: AgreementPlan,
    out: str | Path,
    *,
    videos: int | None = None,
    jobs: int = 1,
    progress: bool = True,
) -> dict[str, Any]:
    """Run (or resume) ``plan`` into ``out`` and write its report; returns the summary. ``videos``:
    how many of the most disagreeing episodes get a video (None: :data:`DEFAULT_VIDEOS`, none in
    a ``truth_noise`` run, which has no world model to show). ``jobs``:
    cells run at once, each in a process of its own (the env's one torch thread each), the
    process's CPUs shared out among them (a world-model cell's rollouts in that many groups on
    threads, ``config.model.rollout_threads``; the records do not depend on it)."""
    from tqdm import tqdm

    from m4world_env import zoo
    from world_model.rollout.shards import usable_cpus

    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"jobs must be a positive integer, got {jobs!r}")
    videos = _videos_of(plan, videos)
    out = Path(out)
    load_bundle_files(plan.checkpoint)  # a missing or broken bundle is refused before any cell runs
    _check_plan(plan, out)
    todo = cells(plan)
    done = [json.loads(c.path(out).read_text()) for c in todo if c.path(out).exists()]
    # The world model's cells first: they take most of the time, the ground truth's fill the gaps.
    left = sorted((c for c in todo if not c.path(out).exists()), key=lambda c: c.backend != "world_model")
    groups = max(1, usable_cpus() // jobs)
    tracker = Progress(out, plan, todo, jobs)
    bar = tqdm(total=len(todo), initial=len(done), desc="agreement", unit="cell", disable=not progress)
    tracker.update(done, left[:jobs])
    if jobs == 1:
        for i, cell in enumerate(left):
            done.append(timed_cell(cell, plan, out, groups))
            tracker.update(done, left[i + 1 : i + 2])
            bar.update(1)
    else:
        import multiprocessing
        from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(jobs, context, exit_with_parent, (os.getpid(),)) as pool:
            running = {pool.submit(timed_cell, c, plan, out, groups): c for c in left}
            try:
                while running:
                    finished, _ = wait(running, timeout=PROGRESS_SECONDS, return_when=FIRST_COMPLETED)
                    for future in finished:
                        running.pop(future)
                        done.append(future.result())
                        bar.update(1)
                    tracker.update(done, list(running.values())[:jobs])
            except BaseException:
                pool.shutdown(cancel_futures=True)  # a failed cell stops the run; the finished cells are kept
                raise
    bar.close()
    tracker.update(done, [])
    records = [r for c in sorted(done, key=lambda c: (c["scenario"], c["seed"], c["backend"])) for r in c["records"]]
    members = {
        m.name: {"family": m.family, "citation": m.citation, "description": m.description}
        for m in (zoo.member(p) for p in plan.policies)
    }
    header = RunHeader(plan.model_side, plan.scenarios, plan.seeds, plan.steps, tracker.wall_seconds)
    summary = build_summary(records, header, members=members, top_k=max(videos, DEFAULT_TOP_K))
    if videos:
        summary["videos"] = write_videos(plan, summary["disagreements"][:videos], out / "videos", out)
    tracker.update(done, [])
    # The run's wall time, videos included, over every invocation that worked on it; and the
    # cells' own seconds, which add up to more when several jobs ran at once.
    summary["seconds"] = tracker.wall_seconds
    summary["cell_seconds"] = sum(c["seconds"] for c in done)
    summary["jobs"] = jobs
    _write_json(out / "summary.json", summary)
    _write_text(out / "report.md", markdown_report(summary))
    scatter_plot(summary, out / "scatter.png")
    return summary


def write_videos(
    plan: AgreementPlan, episodes: Sequence[dict[str, Any]], folder: Path, relative_to: Path
) -> dict[str, str]:
    """A side-by-side video of each episode (a summary's ``disagreements`` entries); returns each
    episode's key and the video's path relative to ``relative_to``. A video already there is kept."""
    from m4world_env.agreement.video import side_by_side_video

    out: dict[str, str] = {}
    for ep in episodes:
        path = folder / f"{ep['policy']}__{ep['scenario']}__seed{ep['seed']}.mp4"
        if not path.exists():
            side_by_side_video(
                ep["policy"], ep["scenario"], int(ep["seed"]), plan.steps, plan.checkpoint, path, dtype=plan.dtype
            )
        out[ep["key"]] = path.relative_to(relative_to).as_posix()
    return out


def default_plan(*, full: bool = False, checkpoint: str | None = None) -> AgreementPlan:
    """The default run (or the ``--full`` one) over the whole zoo."""
    from m4world_env import zoo

    return AgreementPlan(
        policies=tuple(zoo.members()),
        scenarios=FULL_SCENARIOS if full else DEFAULT_SCENARIOS,
        seeds=tuple(range(FULL_SEEDS if full else DEFAULT_SEEDS)),
        steps=FULL_STEPS if full else DEFAULT_STEPS,
        checkpoint=checkpoint,
    )


def _videos_of(plan: AgreementPlan, videos: int | None) -> int:
    """:func:`run_agreement`'s ``videos`` checked and settled (None: its default)."""
    if videos is None:
        return DEFAULT_VIDEOS if plan.truth_noise is None else 0
    if videos and plan.truth_noise is not None:
        raise ValueError(
            "videos show the world model beside the ground truth; a --truth-noise run has none: --videos 0"
        )
    return videos


def minutes(seconds: float) -> str:
    return f"{seconds / 60:.1f} min" if math.isfinite(seconds) else "?"
