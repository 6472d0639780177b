"""The ``m4world`` command line: one subcommand per job (demo, record, import, eval, train, export, bench, ...)."""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

from m4world_env.agreement import (
    DEFAULT_SCENARIOS,
    DEFAULT_SEEDS,
    DEFAULT_VIDEOS,
    FULL_SCENARIOS,
    FULL_SEEDS,
)
from m4world_env.bench import BENCHMARKS, DEVICE_BENCHMARKS, SUITE
from m4world_env.config import ACTION_TYPES
from world_model.cli_args import check_in_folder as _check_in_folder
from world_model.cli_args import check_out as _check_out
from world_model.cli_args import non_negative_int as _non_negative_int
from world_model.cli_args import positive_float as _positive_float
from world_model.cli_args import positive_int as _positive_int
from world_model.cli_args import seed as _seed
from world_model.precision import DTYPES
from world_model.streaming import STREAMING_BOUNDS

VIDEO_SUFFIXES = (".mp4", ".mkv", ".mov")  # containers that take the demo's H.264
# m4world agreement's default jobs: each holds a world model and a batch of ~30 rollouts (~2 GB).
MAX_DEFAULT_JOBS = 4


def default_jobs() -> int:
    """The CPUs this process may run on, at most :data:`MAX_DEFAULT_JOBS`."""
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return max(1, min(usable, MAX_DEFAULT_JOBS))


def _cmd_demo(args: argparse.Namespace) -> int:
    import cv2
    import gymnasium as gym
    import imageio.v2 as imageio
    import numpy as np

    import m4world_env  # noqa: F401  (registers M4World-v0)
    from m4world_env.evaluate import make_policy

    out = Path(args.out)
    if out.suffix.lower() not in VIDEO_SUFFIXES:
        raise ValueError(f"--out {args.out}: give a video file ending in {', '.join(VIDEO_SUFFIXES)}")
    _check_out(args.out, "file")
    env = gym.make(
        "M4World-v0", scenario=args.scenario, backend=args.backend, checkpoint=args.checkpoint, render_mode="rgb_array"
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_name(f".{out.stem}.partial{out.suffix}")  # an earlier video stays whole until this one is
    obs, info = env.reset(seed=args.seed)
    policy = make_policy(args.policy, env)  # after reset: same policy seed as `m4world eval` for this seed
    fps = env.metadata["render_fps"]
    steps = 0

    def frame() -> np.ndarray:
        img = env.render()
        img = cv2.resize(img, (img.shape[1] * args.scale, img.shape[0] * args.scale), interpolation=cv2.INTER_NEAREST)
        # H.264 wants even sizes: pad one black row/column rather than let ffmpeg rescale.
        return np.pad(img, ((0, img.shape[0] % 2), (0, img.shape[1] % 2), (0, 0)))

    started = time.perf_counter()
    try:
        with imageio.get_writer(partial, fps=fps, codec="libx264", quality=8, macro_block_size=2) as writer:
            writer.append_data(frame())
            while True:
                obs, _r, terminated, truncated, info = env.step(policy(obs, info))
                writer.append_data(frame())
                steps += 1
                if terminated or truncated or (args.steps and steps >= args.steps):
                    break
        partial.replace(out)
    finally:
        partial.unlink(missing_ok=True)
    elapsed = time.perf_counter() - started
    wm = getattr(env.unwrapped.backend, "wm", None)  # the world-model backend's loaded bundle
    env.close()
    metrics = info["episode_metrics"]
    precision = f", DiT dtype {wm.dtype}" if wm is not None else ""
    print(
        f"wrote {out} ({steps} steps in {elapsed:.1f} s with rendering and encoding, scenario {args.scenario}, "
        f"backend {args.backend}{precision}, seed {args.seed})"
    )
    print(
        "episode score: "
        + ", ".join(f"{k}={metrics[k]:.3f}" for k in ("pdms", "progress", "collision", "off_road", "comfort", "return"))
    )
    return 0


def _cmd_record(args: argparse.Namespace) -> int:
    from m4world_env.recorder import RecordConfig, record
    from m4world_env.scenario import list_scenarios
    from world_model.model.config import get_preset

    _check_out(args.out, "folder")
    sensors = get_preset(args.preset).sensors  # the clips must match the model that trains on them
    scenarios = list_scenarios() if args.scenario == ["all"] else args.scenario
    cfg = RecordConfig(
        scenarios=scenarios,
        episodes=args.episodes,
        out=Path(args.out),
        seed=args.seed,
        randomize=not args.no_randomize,
        duration=args.duration,
        height=args.height or sensors.height,
        width=args.width or sensors.width,
        lidar=sensors.lidar,
        bev=sensors.bev,
        exclude_categories=tuple(args.exclude_category or ()),
        action_type=args.action_type,
        styles=tuple(args.styles),
    )
    names = record(cfg, workers=args.workers)
    print(f"{len(names)} clips in {args.out}")
    return 0


def _cmd_import_nuscenes(args: argparse.Namespace) -> int:
    from world_model.data.nuscenes_import import NuScenesImportConfig, import_nuscenes

    _check_out(args.out, "folder")
    _check_out(args.scenarios, "folder", "--scenarios")
    cfg = NuScenesImportConfig(
        dataroot=Path(args.dataroot),
        version=args.version,
        out=Path(args.out),
        scenes=tuple(args.scenes or ()),
        preset=args.preset,  # the clips match this preset's sensors, and so must the dataset's other clips
    )
    names = import_nuscenes(cfg)
    print(f"{len(names)} clips in {args.out}: {', '.join(names)}")
    if args.scenarios:
        from m4world_env.replay import write_replay_scenarios

        paths = write_replay_scenarios(args.out, names, args.scenarios)
        print(f"{len(paths)} log-replay scenarios in {args.scenarios} (m4world eval --scenarios FILE)")
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    from world_model.eval.report import ReportRequest, report_bundle

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    request = ReportRequest(
        checkpoint=args.checkpoint,
        evalset=args.evalset,
        out=args.out,
        seed=args.seed,
        seeds=args.seeds,
        dtype=args.dtype,
        context_frames=args.context_frames,
        clips_prefix=args.clips_prefix,
        max_clips=args.max_clips,
        baseline=args.baseline,
        teacher=args.teacher,
        adapters=tuple(args.adapters or ()),
        refresh_steps=tuple(_step_list(s) for s in args.refresh_steps),
        sink_frames=tuple(args.sink_frames),
    )
    result = report_bundle(request)
    print(result.markdown)
    if result.written:
        md, js = result.written
        print(f"wrote {md} and {js}")
    return 0


def _step_list(text: str) -> tuple[int, ...]:
    """ "0,3" -> (0, 3): a --refresh-steps value (world_model.streaming checks the indices)."""
    try:
        return tuple(int(k) for k in text.split(","))
    except ValueError:
        raise ValueError(f"--refresh-steps takes comma-separated step indices such as 0 or 1,3, got {text!r}") from None


def _cmd_eval(args: argparse.Namespace) -> int:
    _check_out(args.out, "folder" if args.report else "file")
    if args.report and args.ray is not None:
        raise ValueError("--report scores the world model on one machine; --ray runs policy episodes only")
    if args.report:
        return _cmd_report(args)
    from m4world_env import zoo
    from m4world_env.evaluate import EvalRequest, evaluate, format_table, is_zoo_policy, write_report
    from m4world_env.scenario import list_scenarios

    if args.workers is not None and args.ray is None:
        raise ValueError("--workers spreads the episodes over Ray workers: add --ray [ADDRESS]")
    if args.ray:
        from m4world_env.cluster import split_address

        try:
            split_address(args.ray)
        except ValueError as e:
            raise ValueError(f"--ray: {e}") from None
    scenarios = list_scenarios() if args.scenarios == ["all"] else args.scenarios
    if is_zoo_policy(args.policy):
        zoo.member(args.policy)  # a version the zoo does not have is refused before any env is built
    request = EvalRequest(
        args.policy,
        scenarios,
        episodes=args.episodes,
        seed=args.seed,
        backend=args.backend,
        checkpoint=args.checkpoint,
        max_steps=args.max_steps,
    )
    if args.ray is None:
        report = evaluate(request)
    else:
        from m4world_env.cluster import evaluate_on_ray, require_ray

        try:
            require_ray()
        except ImportError as e:  # a user's missing extra: one line, as a bad option
            raise ValueError(str(e)) from None
        report = evaluate_on_ray(request, workers=args.workers, address=args.ray or None)
    print(format_table(report))
    if "cluster" in report:
        c = report["cluster"]
        print(f"Ray: {c['workers']} workers, {c['workers_lost']} lost, {c['episodes_rerun']} episodes re-run")
    if args.out:
        write_report(report, args.out)
        print(f"wrote {args.out}")
    return 0


def _cmd_agreement(args: argparse.Namespace) -> int:
    from m4world_env import zoo
    from m4world_env.agreement.run import AgreementPlan, default_plan, run_agreement
    from m4world_env.scenario import load_scenario

    _check_out(args.out, "folder")
    if args.checkpoint is not None and not Path(args.checkpoint).is_dir():
        raise ValueError(f"--checkpoint {args.checkpoint}: no bundle folder there")
    base = default_plan(full=args.full, checkpoint=args.checkpoint)
    policies = tuple(zoo.member(p).name for p in args.policies) if args.policies else base.policies
    scenarios = tuple(args.scenarios) if args.scenarios else base.scenarios
    seeds = tuple(range(args.seed, args.seed + (args.seeds or len(base.seeds))))
    plan = AgreementPlan(
        policies=policies,
        scenarios=scenarios,
        seeds=seeds,
        steps=args.steps or base.steps,
        checkpoint=args.checkpoint,
        truth_noise=args.truth_noise,
        dtype=args.dtype,
    )
    for name in scenarios:
        load_scenario(name)  # an unknown or broken scenario is refused now, not after the first cells
    _print_agreement(run_agreement(plan, args.out, videos=args.videos, jobs=args.jobs), Path(args.out))
    return 0


def _print_agreement(summary: dict, out: Path) -> None:
    from m4world_env.agreement.run import minutes

    a = summary["agreement"]

    def num(x: float | None) -> str:
        return "n/a" if x is None else f"{x:.3f}"

    print(
        f"{a['policies']} policies, {a['episodes']} episode pairs in {minutes(summary['seconds'])}: "
        f"Pearson r {num(a['pearson'])}, Spearman {num(a['spearman'])}, Kendall {num(a['kendall'])}, "
        f"MMRV {num(a['mmrv'])}, mean |dPDMS| {num(a['mean_abs_delta'])}, "
        f"collision agreement {num(a['collision_agreement'])}"
    )
    print(f"wrote {out / 'report.md'}, summary.json, scatter.png")


def _cmd_zoo(args: argparse.Namespace) -> int:
    from m4world_env import zoo

    rows = [(m.citation, m.family, str(m.seed), m.description) for m in zoo.members().values()]
    widths = [max(len(r[i]) for r in rows) for i in range(3)]
    for r in rows:
        print("  ".join(c.ljust(w) for c, w in zip(r[:3], widths, strict=True)) + "  " + r[3])
    return 0


def _cmd_scenarios(args: argparse.Namespace) -> int:
    from m4world_env.scenario import list_scenarios, load_scenario
    from m4world_env.traffic.bridge import check_reset

    targets = args.check or list_scenarios()
    for name in targets:
        s = load_scenario(name)
        if args.check is not None:
            check_reset(s, str(name))
        print(
            f"{s.name:32s} road={s.road.type:13s} weather={s.weather:6s} time={s.time_of_day:5s} duration={s.duration}s"
        )
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    from world_model.bundle import export_bundle

    _check_in_folder(args.run, "--run")
    _check_out(args.out, "folder")
    print(f"wrote {export_bundle(args.run, args.out)}")
    return 0


def _cmd_tune_range_head(args: argparse.Namespace) -> int:
    from m4world_env.range_tuning import tune

    _check_out(args.out, "folder")
    record = tune(args.checkpoint, Path(args.out), args.seeds, args.steps, args.train_steps)
    print(json.dumps(record, indent=1))
    print(f"wrote {args.out}")
    return 0


# m4world tune-range-head's episodes: seeds apart from the benchmarks' and the agreement report's (0-15).
TUNING_SEEDS = (100, 101, 102, 103)


# How m4world streaming spells each streaming setting in error messages.
STREAMING_FLAGS = {
    "denoising_steps": "--denoising-steps",
    "context_refresh": "--[no-]refresh",
    "refresh_steps": "--refresh-steps",
    "sink_frames": "--sink-frames",
    "first_frame_steps": "--first-frame-steps",
    "first_frame_guidance": "--first-frame-guidance",
    "one_step_first_frame": "--[no-]one-step-first-frame",
}


def _cmd_streaming(args: argparse.Namespace) -> int:
    from world_model.bundle import load_bundle_files, set_streaming
    from world_model.streaming import REFRESH_EVERY_STEP, STREAMING_FILE, StreamingConfig, check_changes

    changes = {
        "denoising_steps": args.denoising_steps,
        "sink_frames": args.sink_frames,
        "first_frame_steps": args.first_frame_steps,
        "first_frame_guidance": args.first_frame_guidance,
        "one_step_first_frame": args.one_step_first_frame,
    }
    if args.refresh_steps is not None:
        every = args.refresh_steps == REFRESH_EVERY_STEP
        changes["refresh_steps"] = REFRESH_EVERY_STEP if every else _step_list(args.refresh_steps)
    changes["context_refresh"] = args.refresh
    changes = check_changes({k: v for k, v in changes.items() if v is not None}, STREAMING_FLAGS)
    files = load_bundle_files(args.checkpoint)
    current = StreamingConfig.from_dict(files.streaming or {}, str(files.path / STREAMING_FILE))
    chosen = current.override(changes, STREAMING_FLAGS)
    if args.write:
        set_streaming(files.path, chosen)
        print(f"wrote {files.path / STREAMING_FILE} and its manifest entry")
    print(json.dumps(chosen.to_dict()))
    return 0


SUITE_DEFAULTS = {"out": "out/bench", "evalset": "data/evalset", "device": "cpu"}


def _cmd_bench(args: argparse.Namespace) -> int:
    import subprocess

    from m4world_env.bench import benchmark_command, suite_command

    if args.name is not None:
        given = [f"--{key}" for key in ("only", *SUITE_DEFAULTS) if getattr(args, key) is not None]
        if given:
            raise ValueError(
                f"{', '.join(given)} choose the suite's runs; a single benchmark takes its own options after its "
                f"name: m4world bench {args.name} --help"
            )
        return subprocess.run(benchmark_command(args.name, args.options)).returncode
    settings = {key: getattr(args, key) or default for key, default in SUITE_DEFAULTS.items()}
    _check_out(settings["out"], "folder")
    out = Path(settings["out"])
    out.mkdir(parents=True, exist_ok=True)
    for name in args.only or SUITE:
        cmd = suite_command(name, out, settings["evalset"], settings["device"])
        print("$", " ".join(cmd), flush=True)
        subprocess.run(cmd, check=True)
    return 0


def _cmd_text_embeddings(args: argparse.Namespace) -> int:
    from m4world_env.scenario import list_scenarios
    from m4world_env.text_embeddings import precompute_text_embeddings

    _check_out(args.out, "file")
    scenarios = list_scenarios() if args.scenario == ["all"] else args.scenario
    path, prompts, pooled = precompute_text_embeddings(
        scenarios, args.out, args.episodes, args.seed, args.steps, args.checkpoint
    )
    print(f"{prompts} prompts and {pooled} object texts in {path}; use it with M4WORLD_TEXT_EMBEDDINGS={path}")
    return 0


def _cmd_evalset(args: argparse.Namespace) -> int:
    from m4world_env.evalset import record_evalset

    _check_out(args.out, "folder")
    clips = record_evalset(args.out)
    print(f"{len(clips)} evaluation clips in {args.out}")
    return 0


def _cmd_gallery(args: argparse.Namespace) -> int:
    from m4world_env.gallery import make_gallery

    _check_out(args.out, "folder")
    for path in make_gallery(args.out, seconds=args.seconds, height=args.height, width=args.width):
        print(f"wrote {path}")
    return 0


def _add_demo_parser(sub: argparse._SubParsersAction) -> None:
    d = sub.add_parser("demo", help="run a scenario and write an mp4 of the sensor mosaic")
    d.add_argument("--scenario", default="highway_sunny_day")
    d.add_argument("--backend", default="world_model", choices=("procedural", "world_model"))
    d.add_argument("--checkpoint", default=None)
    d.add_argument("--policy", default="idm", help="built-in (random, lane_keeping, idm) or module:callable")
    d.add_argument("--seed", type=_seed, default=0)
    d.add_argument(
        "--steps", type=_non_negative_int, default=0, help="stop after N steps (0 = the scenario's duration)"
    )
    d.add_argument("--out", default="out/demo.mp4")
    d.add_argument("--scale", type=_positive_int, default=3, help="integer upscaling of the mosaic in the video")
    d.set_defaults(func=_cmd_demo)


def _add_record_parser(sub: argparse._SubParsersAction) -> None:
    r = sub.add_parser("record", help="record training clips (procedural sensors) from scenarios")
    r.add_argument("--scenario", nargs="+", required=True, help="scenario names/paths, or 'all'")
    r.add_argument("--episodes", type=_positive_int, default=1)
    r.add_argument("--out", required=True)
    r.add_argument("--seed", type=_seed, default=0)
    r.add_argument("--duration", type=_positive_float, default=None, help="override the scenarios' duration (s)")
    r.add_argument("--preset", default="default", help="model preset whose sensors (views, LiDAR, BEV) the clips match")
    r.add_argument("--height", type=_positive_int, default=None, help="camera height (default: the preset's)")
    r.add_argument("--width", type=_positive_int, default=None, help="camera width (default: the preset's)")
    r.add_argument("--no-randomize", action="store_true", help="record the scenarios exactly as written")
    r.add_argument("--exclude-category", action="append", help="drop scripted objects of this category")
    r.add_argument(
        "--styles",
        nargs="+",
        default=["steady"],
        help="ego driving styles (steady, speed_changes, lane_changes, weaving), cycled over the episodes "
        "(seed s drives styles[s %% len(styles)])",
    )
    r.add_argument(
        "--action-type",
        default="discrete_meta",
        choices=ACTION_TYPES,
        help="the ego's action space; continuous brakes and accelerates beyond the meta-actions' target speeds",
    )
    r.add_argument(
        "--workers",
        type=_positive_int,
        default=1,
        help="record clips in this many processes (each clip identical to a serial run's; e.g. the CPU count)",
    )
    r.set_defaults(func=_cmd_record)


def _add_import_parser(sub: argparse._SubParsersAction) -> None:
    imp = sub.add_parser("import", help="import real driving logs as training clips").add_subparsers(
        dest="source", required=True
    )
    n = imp.add_parser("nuscenes", help="nuScenes scenes -> clips (needs the [nuscenes] extra; docs/data.md)")
    n.add_argument("--dataroot", required=True, help="nuScenes root (holds samples/, sweeps/ and the version dir)")
    n.add_argument("--version", default="v1.0-mini", help="v1.0-mini, v1.0-trainval, ...")
    n.add_argument("--out", required=True, help="dataset directory to write")
    n.add_argument("--scenes", nargs="+", default=None, help="scene names (default: all of the version)")
    n.add_argument("--preset", default="default", help="model preset whose sensors (views, LiDAR, BEV) the clips match")
    n.add_argument("--scenarios", default=None, help="also write a log-replay scenario YAML per scene here")
    n.set_defaults(func=_cmd_import_nuscenes)


def _add_eval_parser(sub: argparse._SubParsersAction) -> None:
    e = sub.add_parser("eval", help="score a policy over scenarios (PDM-style)")
    e.add_argument("--policy", default="idm")
    e.add_argument("--scenarios", nargs="+", default=["all"])
    e.add_argument("--episodes", type=_positive_int, default=1)
    e.add_argument("--seed", type=_seed, default=0)
    e.add_argument(
        "--seeds",
        type=_positive_int,
        default=3,
        help="--report: noise seeds per model row (--seed, --seed + 1, ...): scores are their mean, with the spread",
    )
    e.add_argument("--backend", default="procedural", choices=("procedural", "world_model"))
    e.add_argument("--checkpoint", default=None)
    e.add_argument("--max-steps", type=_positive_int, default=None, help="stop each episode after N steps")
    e.add_argument("--out", default=None, help="write the JSON report here (with --report: a folder)")
    e.add_argument(
        "--ray",
        nargs="?",
        const="",
        default=None,
        metavar="ADDRESS",
        help="run the episodes as tasks on Ray workers (the cluster extra): alone, the instance RAY_ADDRESS "
        "names or a new local one; or auto, HOST:PORT, ray://HOST:10001. Same seeds and table as without it",
    )
    e.add_argument(
        "--workers",
        type=_positive_int,
        default=None,
        help="--ray: the number of Ray workers (actors of one CPU each; default: one per CPU of the instance)",
    )
    _add_eval_report_arguments(e)
    e.set_defaults(func=_cmd_eval)


def _add_eval_report_arguments(e: argparse.ArgumentParser) -> None:
    """The flags of ``m4world eval --report``: the evaluation set, the extra rows and how they run."""
    e.add_argument(
        "--report",
        action="store_true",
        help="score the world model against the procedural ground truth on an evaluation set "
        "(the paper's Tables 1-2: oracle, autoencoder, road-only (no objects), [geometry-only], student, "
        "refresh-off ablation, [teacher])",
    )
    e.add_argument("--evalset", default="data/evalset", help="--report: evaluation clips (m4world evalset)")
    e.add_argument("--max-clips", type=_non_negative_int, default=0, help="--report: use only the first N clips")
    e.add_argument(
        "--clips-prefix",
        default="",
        help="--report: use only the clips whose names start with this (e.g. long_: the three 60 s rollouts)",
    )
    e.add_argument("--baseline", default=None, help="--report: bundle of the geometry-only baseline (a row)")
    e.add_argument("--teacher", default=None, help="--report: a teacher export, RUN/teacher/model (a row)")
    e.add_argument(
        "--adapters",
        nargs="+",
        default=None,
        help="--report: LoRA adapters (names in the bundle's adapters/ or $M4WORLD_ADAPTERS, or paths) applied "
        "as the env does (each to the student or the reference model it was trained on) for an extra row, "
        "student_adapted (per-category existence: report.json's per_category)",
    )
    e.add_argument(
        "--dtype",
        default="auto",
        choices=DTYPES,
        help="--report: the DiTs' precision, as the env's config model.dtype (auto: bf16 only where the CPU "
        "multiplies it faster than float32); part of each cached row's key",
    )
    e.add_argument(
        "--context-frames",
        type=_positive_int,
        default=None,
        help="--report: run the student rows with a rolling window of N frames instead of the one the "
        "checkpoint was trained with (a study of the window; part of those rows' key)",
    )
    e.add_argument(
        "--refresh-steps",
        action="append",
        default=[],
        metavar="K[,K...]",
        help="--report: an extra student row refreshing the context frame at these denoising steps only "
        "(0 = the first; config model.refresh_steps), e.g. --refresh-steps 0 --refresh-steps 3 for two rows, "
        "student_refresh_0 and student_refresh_3",
    )
    e.add_argument(
        "--sink-frames",
        action="append",
        type=_non_negative_int,
        default=[],
        metavar="N",
        help="--report: extra student rows keeping each rollout's first N frames in context beside the "
        "window (config model.sink_frames): student_sink_N, and student_refresh_K_sink_N for each "
        "--refresh-steps row",
    )


def _add_train_parser(sub: argparse._SubParsersAction) -> None:
    from world_model.train.cli import DESCRIPTION, EPILOG, add_train_arguments, run_train

    t = sub.add_parser(
        "train",
        help="train world-model stages (resumable: rerun the same command)",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_train_arguments(t)
    t.set_defaults(func=run_train)


def _add_export_parser(sub: argparse._SubParsersAction) -> None:
    x = sub.add_parser("export", help="collect a training run's stage exports into a checkpoint bundle")
    x.add_argument("--run", required=True)
    x.add_argument("--out", required=True)
    x.set_defaults(func=_cmd_export)


def _add_tune_range_head_parser(sub: argparse._SubParsersAction) -> None:
    t = sub.add_parser(
        "tune-range-head",
        help="tune a bundle's LiDAR range head on the env's own rollouts (m4world_env/range_tuning.py)",
    )
    t.add_argument("--checkpoint", default=None, help="the bundle to tune (default: the shipped one)")
    t.add_argument("--out", required=True, help="folder of the new bundle (may be --checkpoint's)")
    t.add_argument("--seeds", type=_seed, nargs="+", default=list(TUNING_SEEDS), help="one episode per scenario each")
    t.add_argument("--steps", type=_positive_int, default=40, help="policy steps per episode (at most)")
    t.add_argument("--train-steps", type=_positive_int, default=1000)
    t.set_defaults(func=_cmd_tune_range_head)


def _add_streaming_parser(sub: argparse._SubParsersAction) -> None:
    st = sub.add_parser(
        "streaming",
        help="show (or, with --write, set) a bundle's streaming.json: how the env and the report run the student",
    )
    st.add_argument("--checkpoint", default=None, help="bundle folder (default: the shipped one)")
    st.add_argument(
        "--denoising-steps",
        type=int,
        default=None,
        help=f"denoising steps per chunk, {STREAMING_BOUNDS['denoising_steps']}",
    )
    st.add_argument(
        "--refresh-steps",
        default=None,
        help="the denoising steps that refresh the context frame: comma-separated indices (0 = the first, "
        "-1 = the last; each -n <= k < n for n denoising steps), or all",
    )
    st.add_argument(
        "--refresh",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="turn the latent context refresh on or off (--no-refresh)",
    )
    st.add_argument(
        "--sink-frames",
        type=int,
        default=None,
        help=f"first frames of a rollout kept in context beside the window, {STREAMING_BOUNDS['sink_frames']}",
    )
    st.add_argument(
        "--first-frame-steps",
        type=int,
        default=None,
        help="the reference model's Euler steps for a rollout's first frame (a reset), "
        f"{STREAMING_BOUNDS['first_frame_steps']}",
    )
    st.add_argument(
        "--first-frame-guidance",
        type=float,
        default=None,
        help="the cameras' classifier-free guidance scale of a rollout's first frame, "
        f"{STREAMING_BOUNDS['first_frame_guidance']}",
    )
    st.add_argument(
        "--one-step-first-frame",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="a rollout's first frame from controls in one step of the bundle's first-frame model, when it has "
        "one (--no-one-step-first-frame: the reference model's --first-frame-steps guided steps)",
    )
    st.add_argument("--write", action="store_true", help="write the result into the bundle (re-hashed manifest)")
    st.set_defaults(func=_cmd_streaming)


def _add_bench_parser(sub: argparse._SubParsersAction) -> None:
    b = sub.add_parser(
        "bench",
        help="run a benchmark (m4world bench NAME [its options]) or the suite (JSON per benchmark in --out)",
        description="m4world bench NAME [OPTIONS]: one benchmark, its options after its name "
        "(m4world bench NAME --help). m4world bench [--only NAME ...]: the suite, default options.",
    )
    b.add_argument("name", nargs="?", choices=BENCHMARKS, metavar="NAME", help=f"one of {', '.join(BENCHMARKS)}")
    b.add_argument("options", nargs=argparse.REMAINDER, help="the benchmark's own options")
    b.add_argument("--only", nargs="+", choices=SUITE, help="suite: run these only")
    b.add_argument("--out", default=None, help=f"suite: folder of the JSON files (default {SUITE_DEFAULTS['out']})")
    b.add_argument(
        "--evalset",
        default=None,
        help=f"suite: evaluation set of judge and first_frame (default {SUITE_DEFAULTS['evalset']})",
    )
    b.add_argument(
        "--device",
        default=None,
        help=f"suite: where {', '.join(DEVICE_BENCHMARKS)} run: cpu, cuda[:N] or auto (default cpu)",
    )
    b.set_defaults(func=_cmd_bench)


def _add_text_embeddings_parser(sub: argparse._SubParsersAction) -> None:
    te = sub.add_parser(
        "text-embeddings",
        help="precompute the text embeddings of some episodes, for a machine without the text encoder",
    )
    te.add_argument("--scenario", nargs="+", required=True, help="scenario names/paths, or 'all'")
    te.add_argument("--episodes", type=_positive_int, default=1, help="seeds --seed .. --seed + episodes - 1")
    te.add_argument("--seed", type=_seed, default=0)
    te.add_argument("--steps", type=_positive_int, default=None, help="steps per episode (default: to its end)")
    te.add_argument("--checkpoint", default=None, help="bundle whose text encoder to use (default: the shipped one)")
    te.add_argument("--out", required=True, help="the .npz file to write")
    te.set_defaults(func=_cmd_text_embeddings)


def _add_evalset_parser(sub: argparse._SubParsersAction) -> None:
    v = sub.add_parser("evalset", help="record the held-out evaluation set (seeds disjoint from training)")
    v.add_argument("--out", default="data/evalset")
    v.set_defaults(func=_cmd_evalset)


def _add_gallery_parser(sub: argparse._SubParsersAction) -> None:
    g = sub.add_parser("gallery", help="render PNG mosaics of scenarios under several weathers/times")
    g.add_argument("--out", default="docs/images")
    g.add_argument("--seconds", type=_positive_float, default=3.0)
    g.add_argument("--height", type=_positive_int, default=128)
    g.add_argument("--width", type=_positive_int, default=224)
    g.set_defaults(func=_cmd_gallery)


def _add_agreement_parser(sub: argparse._SubParsersAction) -> None:
    ag = sub.add_parser(
        "agreement",
        help="run the policy zoo on the ground truth and the world model; report how well their scores agree",
    )
    ag.add_argument("--out", required=True, help="the run's folder (resumed when it holds the same run)")
    ag.add_argument("--checkpoint", default=None, help="world-model bundle (default: the shipped one)")
    ag.add_argument(
        "--full",
        action="store_true",
        help=f"the large run: {len(FULL_SCENARIOS)} scenarios, {FULL_SEEDS} seeds (default: "
        f"{len(DEFAULT_SCENARIOS)} scenarios, {DEFAULT_SEEDS} seeds)",
    )
    ag.add_argument("--policies", nargs="+", default=None, help="zoo members (default: all; m4world zoo lists them)")
    ag.add_argument("--scenarios", nargs="+", default=None, help="scenarios (default: the run size's)")
    ag.add_argument("--seeds", type=_positive_int, default=None, help="seeds per scenario (--seed, --seed + 1, ...)")
    ag.add_argument("--seed", type=_seed, default=0, help="the first seed")
    ag.add_argument("--steps", type=_positive_int, default=None, help="policy steps per episode")
    ag.add_argument(
        "--jobs",
        type=_positive_int,
        default=default_jobs(),
        help="cells run at once, each in its own process with one torch thread (default: the CPUs, at most "
        f"{MAX_DEFAULT_JOBS}; each holds a world model and a batch of rollouts, ~2 GB)",
    )
    ag.add_argument(
        "--videos",
        type=_non_negative_int,
        default=None,
        help=f"side-by-side videos of the episodes the backends disagree on most (default: {DEFAULT_VIDEOS}; "
        "none with --truth-noise)",
    )
    ag.add_argument(
        "--truth-noise",
        type=float,
        default=None,
        metavar="SIGMA",
        help="in the world model's place, the ground truth with its cameras seen through Gaussian noise of "
        "SIGMA grey levels: how far two ground truths no policy should tell apart score apart (the floor)",
    )
    ag.add_argument(
        "--dtype",
        default="auto",
        choices=DTYPES,
        help="the world model's DiTs' precision, as the env's config model.dtype (auto: bf16 where the CPU "
        "multiplies it faster than float32)",
    )
    ag.set_defaults(func=_cmd_agreement)


def _add_zoo_parser(sub: argparse._SubParsersAction) -> None:
    z = sub.add_parser("zoo", help="list the zoo's policies that see (names for --policy)")
    z.set_defaults(func=_cmd_zoo)


def _add_scenarios_parser(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser("scenarios", help="list (or validate) scenarios")
    s.add_argument("--check", nargs="*", help="scenario files to validate")
    s.set_defaults(func=_cmd_scenarios)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="m4world", description="M4World-Gym: world-model driving environment")
    sub = p.add_subparsers(dest="command", required=True)
    _add_demo_parser(sub)
    _add_record_parser(sub)
    _add_import_parser(sub)
    _add_eval_parser(sub)
    _add_train_parser(sub)
    _add_export_parser(sub)
    _add_tune_range_head_parser(sub)
    _add_streaming_parser(sub)
    _add_bench_parser(sub)
    _add_text_embeddings_parser(sub)
    _add_evalset_parser(sub)
    _add_gallery_parser(sub)
    _add_agreement_parser(sub)
    _add_zoo_parser(sub)
    _add_scenarios_parser(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ValueError, KeyError, OSError) as e:
        # User errors (bad scenario, option, policy): one clear line, no traceback.
        print(f"m4world {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
