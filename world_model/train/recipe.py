"""The recipe: record training clips, train the whole chain and write a bundle, in one command.

``python -m world_model.train.recipe --out OUT [--device cuda] [--scale gpu|cpu|dry]``

1. records the clips with ``m4world record`` on the machine's cores (``OUT/data``);
2. trains vae -> decoder -> teacher -> tf -> ode -> dmd -> long -> reference -> first_frame -> rollout_decoder ->
   range_head into
   ``OUT/run`` through :func:`world_model.train.stages.train_stage` (the training CLI's entry), each stage at the
   scale's steps and batch size, then the bundle's long-tail adapters (:data:`ADAPTERS`) on the
   bundle's own weights, from the rare object's clips (``OUT/data_rare``);
3. writes the bundle (``OUT/bundle``) and a copy whose every file is at most ``--max-file-mib``
   (``OUT/bundle_parts``: larger files split into ``NAME.partNNN`` with ``SHA256SUMS``; rejoin
   with ``python -m world_model.train.recipe --join OUT/bundle_parts DEST``);
4. writes ``OUT/recipe.json``: each phase's wall time, each stage's steps and final loss.

A scale with a time limit (``gpu``: 9 minutes, ``--time-limit-s``) gives each stage a share of the
time left after recording, its setup (caches, rollouts) included, and stops it there, checkpointed
and exported, even short of its steps (after one step at least): the steps are
upper bounds, sized for an H100, and a slower machine still gets a whole chain in time.

On the GPU machine the text encoder is the dependency-free hash encoder (it has no MiniLM
weights); ``--scale cpu`` keeps the preset's MiniLM. ``--scale dry`` runs the very same command
at the tiny preset and a few steps per stage (the CPU check, ``tests/test_gpu_recipe.py``).
Rerunning resumes: recorded clips are skipped and each stage resumes from its last checkpoint.

``--phases steps`` (not in the default chain) teaches the student to stream in half its denoising
steps (:mod:`world_model.train.student_stages`), ``--phases shallow`` distils it into the scale's
``shallow_depth`` blocks (:mod:`world_model.train.shallow_stage`); ``--episodes N`` records the
first N of the scale's clips per scenario (a quicker run of a few phases).

``--from-bundle BUNDLE --phases P [P ...]`` retrains some phases of a finished bundle at the scale:
``OUT/run`` starts from the bundle's components as stage exports
(:func:`world_model.train.seed_run.seed_run`), only the phases named train, and the bundle is
written from the run as usual. The decoder phases, say, train again on a shipped checkpoint whose
encoder and DiTs stay as they are.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from world_model.model.config import ModelConfig
    from world_model.train.run import StageOptions

from world_model import cli_args
from world_model.train.cli import PIPELINE

CHAIN = PIPELINE  # the training CLI's --all chain, in its order
# The long-tail adapter of the bundle (docs/MODEL_CARD.md), trained on the bundle's own weights:
# name -> (component adapted, extra loss weight inside the rare object's boxes). The reference
# model is the one adapted: it draws the rare object into reset()'s first frame, where the student
# streams on from (docs/experiments.md weighs a student adapter).
RARE_CATEGORY = "tree_truck"
ADAPTERS = {f"{RARE_CATEGORY}_completion": ("reference", 9.0)}
# Phases the recipe trains only when asked (--phases), after the chain: the student taught fewer
# denoising steps, then distilled into fewer blocks.
OPTIONAL_PHASES = ("steps", "shallow")
PHASES = CHAIN + OPTIONAL_PHASES + tuple(ADAPTERS)
DEFAULT_PHASES = CHAIN + tuple(ADAPTERS)
MIB = 1 << 20


@dataclass(frozen=True)
class RecipeScale:
    """What one scale records and trains: preset, clips and (steps, global batch) per stage.

    Every scenario is recorded ``episodes`` times under each of ``seeds`` consecutive base seeds, by
    one ``m4world record`` process per seed and group of ``scenarios_per_process`` scenarios: one
    scenario each gives more processes than scenarios, which keeps every core busy; a few short
    clips are quicker in one process (each process spends seconds starting). The clips do not
    depend on how many processes run at once."""

    preset: str
    episodes: int  # clips per scenario and seed
    seeds: int
    scenarios_per_process: int
    duration_s: float | None  # None: the scenarios' own durations
    rare_episodes: int  # clips of the rare object's scenario with the object, for the adapters
    stages: dict[str, tuple[int, int]] = field(default_factory=dict)
    time_limit_s: float | None = None  # the whole recipe, recording included; None: no limit
    # Under a time limit, each phase's wall time (setup included: caches, rollouts) on the machine
    # the scale is for; a phase gets its proportion of the time left (stage_time_limit). Empty:
    # equal shares.
    phase_seconds: dict[str, float] = field(default_factory=dict)
    # "hash" where the MiniLM weights cannot travel (a GPU machine); None: the preset's (MiniLM)
    text_encoder: str | None = "hash"
    # The shallow phase's student blocks, of the default preset's 10: the shipped student's.
    shallow_depth: int = 5


SCALES = {
    # One H100/H200 in 9 minutes. 216 clips of 20 s as the shipped checkpoint's dataset (about 8 GB):
    # recording runs at about 150 frames/s per core (default preset), so 18 processes on 16 cores
    # take well under a minute; the layout rasters are computed once, on every core. A teacher step
    # takes 0.11 s at batch 4 and at batch 64 alike (the default preset is kernel-launch bound
    # there), so each stage runs at a large batch for its share of the time.
    "gpu": RecipeScale(
        preset="default",
        episodes=12,
        seeds=2,
        scenarios_per_process=1,
        duration_s=20.0,
        rare_episodes=5,
        stages={
            "vae": (4000, 64),
            "decoder": (2000, 64),
            "teacher": (5000, 64),
            "tf": (2000, 32),
            "ode": (400, 16),
            "dmd": (300, 8),
            "long": (100, 8),
            "steps": (300, 8),
            "shallow": (1000, 16),
            "rollout_decoder": (1000, 64),
            "range_head": (1500, 64),
            "camera_decoder": (1000, 64),
            "reference": (1500, 32),
            "first_frame": (1500, 32),
            "lora": (1500, 32),
        },
        time_limit_s=540.0,
        # Each phase's wall time on one H200 with 16 cores, its setup included: the decoder's
        # label maps, the teacher's latent and layout caches, the rollout decoder's rollouts.
        phase_seconds={
            "vae": 60,
            "decoder": 55,
            "teacher": 150,
            "tf": 40,
            "ode": 22,
            "dmd": 30,
            "long": 17,
            "steps": 30,  # not measured on a GPU yet: the long phase's, at its steps
            "shallow": 30,  # not measured on a GPU yet
            "reference": 30,
            "first_frame": 30,  # not measured on a GPU yet: the reference phase's
            "rollout_decoder": 60,
            "range_head": 60,
            "camera_decoder": 60,
            f"{RARE_CATEGORY}_completion": 20,
        },
    ),
    # This 2-core CPU in about 2.7 hours: the shipped checkpoint's dataset and steps (docs/MODEL_CARD.md),
    # with the MiniLM text encoder that is at hand here. The time limit gives each stage its share;
    # rerun the command to resume, with a larger --time-limit-s to go on toward the steps.
    "cpu": RecipeScale(
        preset="default",
        episodes=24,
        seeds=1,
        scenarios_per_process=1,
        duration_s=20.0,
        rare_episodes=5,
        stages={
            "vae": (3000, 16),
            "decoder": (1500, 16),
            "teacher": (3000, 4),
            "tf": (500, 4),
            "ode": (80, 4),
            "dmd": (50, 2),
            "long": (20, 2),
            "steps": (150, 2),
            "shallow": (3000, 4),
            "rollout_decoder": (4500, 16),
            "range_head": (1500, 16),
            "camera_decoder": (4500, 16),
            "reference": (800, 4),
            "first_frame": (1500, 8),
            "lora": (300, 4),
        },
        time_limit_s=9720.0,
        # The shipped checkpoint's stages on this 2-core CPU (docs/MODEL_CARD.md); the adapter's
        # 10 minutes are its training alone, the clips' latents coming from the run's cache.
        phase_seconds={
            "vae": 600,
            "decoder": 300,
            "teacher": 3720,
            "tf": 540,
            "ode": 420,
            "dmd": 660,
            "long": 180,
            "steps": 780,  # 150 steps at 0.19 a second on the 2-core Xeon (AMX), the latents cached
            "shallow": 1500,
            "reference": 720,
            "first_frame": 720,  # its pool's targets and training (the run's latents cached already)
            "rollout_decoder": 1020,
            "range_head": 900,
            "camera_decoder": 1020,
            f"{RARE_CATEGORY}_completion": 600,
        },
        text_encoder=None,
    ),
    # The same command on a CPU: every stage runs, a few steps each.
    "dry": RecipeScale(
        preset="tiny",
        episodes=1,
        seeds=1,
        scenarios_per_process=9,
        duration_s=0.6,
        rare_episodes=1,
        stages={stage: (2, 2) for stage in (*CHAIN, *OPTIONAL_PHASES, "lora")},
        shallow_depth=1,  # of the tiny preset's 2
    ),
}


# The recipe puts the scene where the pixels are: pixel-aligned layout channels (docs/layout.md), at
# 2 rays per latent cell side, which keeps the env's per-frame raster cheap (m4world bench layout).
LAYOUT_SUPERSAMPLE = 2
# An ego that brakes, accelerates and changes lanes, so that actions have consequences to learn.
RECORD_STYLES = ("steady", "speed_changes", "lane_changes", "weaving")
# The long-tail case stays out of the base model's data: the LoRA adapters learn it (docs/MODEL_CARD.md).
EXCLUDED_CATEGORIES = ("tree_truck",)
# The rare clips: the scenario with the rare object, at the base seed the shipped adapters used.
RARE_SCENARIO, RARE_SEED = "tree_truck_highway", 7
# Kept from the time limit for what follows the last stage's training: its export and the bundle.
BUNDLE_RESERVE_S = 15.0


def recipe_config(spec: RecipeScale):  # noqa: ANN201 - a ModelConfig
    """The scale's preset with layout conditioning on (the DiT's channels and the decoder's label
    maps) and the scale's text encoder (the hash encoder needs no download) at the preset's text width."""
    from world_model.model.config import get_preset, with_layout

    cfg = get_preset(spec.preset)
    layout = replace(with_layout(cfg, True).layout, supersample=LAYOUT_SUPERSAMPLE)
    text = cfg.text if spec.text_encoder is None else replace(cfg.text, encoder=spec.text_encoder)
    return replace(cfg, text=text, layout=layout)


def record_clips(out: Path, scale: RecipeScale, workers: int, seed: int) -> int:
    """Record the scale's clips of every scenario into ``out`` with ``workers`` processes at once
    (:class:`RecipeScale`); returns the number of clips in ``out``. A clip depends only on its
    scenario, base seed and episode, so the data is the same whatever ``workers`` is."""
    from m4world_env.scenario import list_scenarios

    # `m4world record --workers N` parallelizes inside one call; these processes per (scenario, seed)
    # are the fan-out that works with every `m4world record`.
    env = {**os.environ, "OMP_NUM_THREADS": "1"}

    def one(job: tuple[list[str], int]) -> None:
        scenarios, base_seed = job
        rare = base_seed == RARE_SEED
        folder, episodes = (rare_dir(out), scale.rare_episodes) if rare else (out, scale.episodes)
        cmd = [sys.executable, "-m", "m4world_env.cli", "record", "--scenario", *scenarios, "--out", str(folder)]
        cmd += ["--episodes", str(episodes), "--preset", scale.preset, "--seed", str(base_seed)]
        cmd += ["--styles", *RECORD_STYLES, "--action-type", "continuous"]
        for category in () if rare else EXCLUDED_CATEGORIES:
            cmd += ["--exclude-category", category]
        if scale.duration_s is not None:
            cmd += ["--duration", str(scale.duration_s)]
        done = subprocess.run(cmd, capture_output=True, text=True, env=env)
        if done.returncode != 0:
            raise RuntimeError(f"recording {', '.join(scenarios)} failed:\n{done.stderr[-2000:]}")

    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        names, n = list_scenarios(), scale.scenarios_per_process
        groups = [names[i : i + n] for i in range(0, len(names), n)]
        jobs = [([RARE_SCENARIO], RARE_SEED)] + [(g, seed + k) for g in groups for k in range(scale.seeds)]
        list(pool.map(one, jobs))
    from world_model.data.clips import sort_index

    sort_index(rare_dir(out))
    return len(sort_index(out))


def rename_adapter(adapter: Path, name: str) -> Path:
    """Move the adapter folder ``adapter`` (``RUN/lora/<case>``) to ``RUN/lora/<name>`` under that
    name, its category (``train.case``) kept; replaces an older one of that name."""
    import shutil

    from world_model.data.clips import write_json_atomic
    from world_model.lora import seal_adapter

    meta_path = adapter / "adapter.json"
    meta = json.loads(meta_path.read_text())
    meta["name"] = name
    write_json_atomic(meta_path, meta)
    target = adapter.with_name(name)
    if target.exists():
        shutil.rmtree(target)
    adapter.rename(target)
    return seal_adapter(target)


def rare_dir(data: Path) -> Path:
    """The rare object's clips, beside the training clips (``data``)."""
    return data.with_name(data.name + "_rare")


def split_files(src: Path, dest: Path, max_bytes: int) -> list[Path]:
    """Copy the files of ``src`` (recursively) to ``dest``, splitting any larger than ``max_bytes``
    into ``NAME.partNNN``; ``dest/SHA256SUMS`` lists every original file. Returns the written files."""
    import shutil

    if dest.exists():
        shutil.rmtree(dest)
    written, sums = [], []
    for file in sorted(p for p in src.rglob("*") if p.is_file()):
        rel = file.relative_to(src)
        target = dest / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        data = file.read_bytes()
        sums.append(f"{hashlib.sha256(data).hexdigest()}  {rel.as_posix()}")
        if len(data) <= max_bytes:
            target.write_bytes(data)
            written.append(target)
            continue
        for k in range(0, len(data), max_bytes):
            part = target.with_name(f"{target.name}.part{k // max_bytes:03d}")
            part.write_bytes(data[k : k + max_bytes])
            written.append(part)
    (dest / "SHA256SUMS").write_text("\n".join(sums) + "\n")
    return written


def join_files(src: Path, dest: Path) -> None:
    """Undo :func:`split_files`: rebuild every file of ``src/SHA256SUMS`` under ``dest``, checked."""
    for line in (src / "SHA256SUMS").read_text().splitlines():
        digest, rel = line.split("  ", 1)
        whole = src / rel
        parts = [whole] if whole.exists() else sorted(whole.parent.glob(f"{whole.name}.part*"))
        data = b"".join(p.read_bytes() for p in parts)
        if hashlib.sha256(data).hexdigest() != digest:
            raise ValueError(f"{rel}: the joined parts do not match SHA256SUMS; copy {src} again")
        (dest / rel).parent.mkdir(parents=True, exist_ok=True)
        (dest / rel).write_bytes(data)


def stage_time_limit(spec: RecipeScale, stages_left: tuple[str, ...], elapsed_s: float) -> float | None:
    """The wall time of ``stages_left[0]``, its setup included: its proportion
    (:attr:`RecipeScale.phase_seconds`) of what the time limit leaves after ``elapsed_s`` (and the
    bundle's reserve) among the phases still to run, so that a phase that ends early, or late,
    passes the difference on. None: the scale has no limit."""
    if spec.time_limit_s is None:
        return None
    left = spec.time_limit_s - elapsed_s - BUNDLE_RESERVE_S
    weights = spec.phase_seconds or dict.fromkeys(stages_left, 1.0)  # none measured: equal shares
    share = weights[stages_left[0]] / sum(weights[s] for s in stages_left)
    return max(1.0, left * share)


@dataclass(frozen=True)
class RecipeOptions:
    """How :func:`run_recipe` runs: the recipe's command-line flags but ``--out`` and ``--join``."""

    scale: str = "gpu"  # a key of SCALES
    device: str = "auto"
    workers: int | None = None  # recording processes; None: every core
    seed: int = 0
    max_file_mib: float = 16.0  # the largest file of bundle_parts/
    progress: bool = True
    time_limit_s: float | None = None  # None: the scale's
    from_bundle: str | Path | None = None  # start the run from this bundle's components
    phases: tuple[str, ...] = DEFAULT_PHASES  # the phases to train
    episodes: int | None = None  # clips per scenario and seed; None: the scale's


def check_run_options(out: Path, options: RecipeOptions) -> None:
    """Refuse, before anything is recorded, the options of :func:`run_recipe` that would fail in a
    later phase: a ValueError (FileNotFoundError for a missing folder) naming the flag and value."""
    from world_model.bundle import CheckpointError, load_bundle_files
    from world_model.train.device import resolve_device

    if options.scale not in SCALES:
        raise ValueError(f"--scale must be one of {', '.join(SCALES)}, got {options.scale!r}")
    unknown = [p for p in options.phases if p not in PHASES]
    if unknown or not options.phases:
        raise ValueError(f"--phases takes one or more of {', '.join(PHASES)}, got {', '.join(unknown) or 'none'}")
    if options.episodes is not None and not (isinstance(options.episodes, int) and options.episodes >= 1):
        raise ValueError(f"--episodes must be a positive integer, got {options.episodes!r}")
    time_limit_s = options.time_limit_s
    if time_limit_s is not None and not 0 < time_limit_s < math.inf:
        raise ValueError(f"--time-limit-s must be a finite number above 0, got {time_limit_s}")
    cli_args.check_out(out, "folder")
    workers, seed, max_file_mib = options.workers, options.seed, options.max_file_mib
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ValueError(f"--workers must be a positive integer (or None: every core), got {workers!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= cli_args.MAX_SEED:
        raise ValueError(f"--seed must be an integer in [0, 2**63 - 1], got {seed!r}")
    if not (isinstance(max_file_mib, int | float) and math.isfinite(max_file_mib) and max_file_mib * MIB >= 1):
        raise ValueError(f"--max-file-mib must be a finite size of at least one byte (1/{MIB} MiB), got {max_file_mib}")
    resolve_device(options.device)
    if options.from_bundle is not None:
        try:
            files = load_bundle_files(
                options.from_bundle
            )  # a folder that is no bundle is named now, not after the recording
        except CheckpointError as e:
            raise ValueError(f"--from-bundle: {e}") from None
        layout = files.model_config.get("layout", {})
        decoders = [p for p in ("decoder", "rollout_decoder") if p in options.phases]
        if decoders and "range_head" not in options.phases and layout.get("range_head"):
            raise ValueError(
                f"--phases {' '.join(options.phases)}: the bundle's range head finishes the decoder it was trained "
                f"on; train it again after {decoders[-1]}: --phases {' '.join(options.phases)} range_head"
            )
        decoders += [p for p in ("range_head",) if p in options.phases]
        if decoders and "camera_decoder" not in options.phases and layout.get("camera_decoder"):
            raise ValueError(
                f"--phases {' '.join(options.phases)}: the bundle's camera decoder keeps the VAE it was trained on; "
                f"train it again after {decoders[-1]}: --phases {' '.join(options.phases)} camera_decoder"
            )


def phase_options(
    phase: str, spec: RecipeScale, config: ModelConfig, seed: int, data: Path, bundle: Path
) -> StageOptions:
    """The stage options of ``phase``: a stage of the chain at the scale's steps and global batch,
    or an adapter (:data:`ADAPTERS`) of ``bundle``'s own weights, from the rare clips beside ``data``."""
    from world_model.model.config import with_student_settings
    from world_model.train.stages import stage_options

    stage = "lora" if phase in ADAPTERS else phase
    steps, batch = spec.stages[stage]
    if phase == "shallow":
        config = with_student_settings(config, spec.shallow_depth)
    settings = {"preset": spec.preset, "config": config, "steps": steps, "batch_size": batch, "seed": seed}
    if phase in ADAPTERS:
        component, box_weight = ADAPTERS[phase]
        base = bundle / "reference.safetensors" if component == "reference" else bundle
        settings |= {"case": RARE_CATEGORY, "case_data": rare_dir(data), "base": str(base), "box_weight": box_weight}
    return stage_options(stage, **settings)


class _Stopwatch:
    """Prints the recipe's phases as they start, with the seconds since the recipe began: a run cut
    short shows where it was."""

    def __init__(self) -> None:
        self.start = time.perf_counter()

    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def say(self, message: str) -> None:
        print(f"[{self.elapsed():6.1f} s] {message}", flush=True)


@dataclass
class _PhaseResults:
    """What the trained phases leave for the summary, by phase."""

    seconds: dict[str, float] = field(default_factory=dict)
    losses: dict[str, float] = field(default_factory=dict)
    steps: dict[str, int] = field(default_factory=dict)


def _train_phases(
    spec: RecipeScale, phases: tuple[str, ...], options: RecipeOptions, out: Path, clock: _Stopwatch
) -> _PhaseResults:
    """Train ``phases`` in order into ``out/run``, each within its share of the time left; the
    adapters adapt the bundle exported (``out/bundle``) just before the first of them."""
    from world_model.bundle import export_bundle
    from world_model.train.run import StageRuntime
    from world_model.train.stages import train_stage

    data, run, bundle = out / "data", out / "run", out / "bundle"
    config = recipe_config(spec)
    results = _PhaseResults()
    for k, phase in enumerate(phases):
        t = time.perf_counter()
        limit = stage_time_limit(spec, phases[k:], t - clock.start)
        stage_options = phase_options(phase, spec, config, options.seed, data, bundle)
        clock.say(
            f"{phase}: up to {stage_options.steps} steps at batch {stage_options.batch_size}"
            + (f", {limit:.0f} s with its setup" if limit else "")
        )
        if phase == next((p for p in phases if p in ADAPTERS), None):  # adapters adapt the bundle's own (bf16) weights
            export_bundle(run, bundle)
        runtime = StageRuntime(progress=options.progress, device=options.device, time_limit_s=limit)
        summary = train_stage("lora" if phase in ADAPTERS else phase, data, run, stage_options, runtime)
        if phase in ADAPTERS:
            rename_adapter(Path(summary["stage_dir"]), phase)
        results.seconds[phase], results.losses[phase] = time.perf_counter() - t, summary["final_loss"]
        results.steps[phase] = summary["step"]
        clock.say(f"{phase}: {summary['step']} steps, loss {summary['final_loss']:.4f}, {results.seconds[phase]:.0f} s")
    return results


def run_recipe(out: Path, options: RecipeOptions) -> dict:
    """Record, train the chain and write the bundle into ``out`` (module docstring); the summary.
    ``options.time_limit_s`` overrides the scale's time limit; ``options.from_bundle`` and
    ``options.phases``: retrain those phases of that bundle (module docstring)."""
    from world_model.bundle import export_bundle

    check_run_options(out, options)
    phases = tuple(p for p in PHASES if p in options.phases)  # the chain's order
    spec = SCALES[options.scale]
    if options.time_limit_s is not None:
        spec = replace(spec, time_limit_s=options.time_limit_s)
    if options.episodes is not None:
        spec = replace(spec, episodes=options.episodes)
    out.mkdir(parents=True, exist_ok=True)
    data, run = out / "data", out / "run"
    data.mkdir(exist_ok=True)
    clock = _Stopwatch()
    clock.say(f"recording {spec.episodes * spec.seeds} clips per scenario into {data}")
    clips = record_clips(data, spec, options.workers or os.cpu_count() or 1, options.seed)
    times = {"record": clock.elapsed()}
    if options.from_bundle is not None:
        from world_model.train.seed_run import seed_run

        clock.say(
            f"run seeded from {options.from_bundle}: {', '.join(seed_run(options.from_bundle, run)) or 'nothing new'}"
        )
    trained = _train_phases(spec, phases, options, out, clock)
    times |= trained.seconds
    t = time.perf_counter()
    bundle = export_bundle(run, out / "bundle")  # the same weights, now with run/lora/ as its adapters
    parts = split_files(bundle, out / "bundle_parts", int(options.max_file_mib * MIB))
    times["bundle"] = time.perf_counter() - t
    summary = {
        "scale": options.scale,
        "from_bundle": None if options.from_bundle is None else str(options.from_bundle),
        "phases": list(phases),
        "preset": spec.preset,
        "device": options.device,
        "clips": clips,
        "seconds": {k: round(v, 1) for k, v in times.items()},
        "total_s": round(clock.elapsed(), 1),
        "time_limit_s": spec.time_limit_s,
        "steps": trained.steps,
        "final_loss": trained.losses,
        "bundle": str(bundle),
        "largest_part_mib": round(max(p.stat().st_size for p in parts) / MIB, 2),
    }
    (out / "recipe.json").write_text(json.dumps(summary, indent=1))
    return summary


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m world_model.train.recipe", description=__doc__.splitlines()[0])
    p.add_argument("--out", help="output folder: data/, run/, bundle/, bundle_parts/, recipe.json")
    p.add_argument(
        "--scale",
        default="gpu",
        choices=sorted(SCALES),
        help="gpu (one H100/H200 in 9 minutes), cpu (a 2-core CPU in 2.7 hours) or dry (a CPU check)",
    )
    p.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    p.add_argument(
        "--workers", type=cli_args.positive_int, default=None, help="recording processes (default: every core)"
    )
    p.add_argument("--seed", type=cli_args.seed, default=0)
    p.add_argument("--max-file-mib", type=cli_args.positive_float, default=16.0, help="largest file of bundle_parts/")
    p.add_argument(
        "--time-limit-s",
        type=cli_args.positive_float,
        default=None,
        help="the whole recipe's wall time (default: the scale's)",
    )
    p.add_argument(
        "--episodes",
        type=cli_args.positive_int,
        default=None,
        help="clips recorded per scenario and seed (default: the scale's); each clip is the same whatever the "
        "number, so fewer are the first of the scale's (a quicker retraining of some phases)",
    )
    p.add_argument("--from-bundle", default=None, help="start the run from this bundle's components (with --phases)")
    p.add_argument(
        "--phases",
        nargs="+",
        default=list(DEFAULT_PHASES),
        help=f"the phases to train, of {' '.join(PHASES)} (default: all but {' '.join(OPTIONAL_PHASES)})",
    )
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--join", nargs=2, metavar=("PARTS", "DEST"), help="rebuild a bundle from bundle_parts/")
    a = p.parse_args(argv)
    try:
        if a.join:
            cli_args.check_in_folder(a.join[0], "--join PARTS")
            cli_args.check_out(a.join[1], "folder", "--join DEST")
            join_files(Path(a.join[0]), Path(a.join[1]))
            return 0
        if not a.out:
            raise ValueError("--out is required (the folder the recipe writes into)")
        options = RecipeOptions(
            scale=a.scale,
            device=a.device,
            workers=a.workers,
            seed=a.seed,
            max_file_mib=a.max_file_mib,
            progress=not a.no_progress,
            time_limit_s=a.time_limit_s,
            from_bundle=a.from_bundle,
            phases=tuple(a.phases),
            episodes=a.episodes,
        )
        summary = run_recipe(Path(a.out), options)
    except (FileNotFoundError, ValueError, RuntimeError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
