"""The benchmarks: every measured figure in the docs comes from one of them. One module each, run as

    m4world bench NAME [OPTIONS]       # one benchmark with its own options (m4world bench NAME --help)
    m4world bench [--only NAME ...]    # the suite: SUITE's benchmarks with their default options

Each runs in a fresh process (``python -m m4world_env.bench.NAME``): its timings and memory figures
are its own, not those of the command that started it or of an earlier benchmark. The modules are
also a library: the tests check what each computes on controlled inputs.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

BENCHMARKS = (
    "action_response",
    "digests",
    "ego_behaviour",
    "env",
    "first_frame",
    "front_reads",
    "judge",
    "lane_markings",
    "layout",
    "layout_ablation",
    "lidar_sectors",
    "longtail",
    "model",
    "policy_reads",
    "precision",
    "record",
    "render",
    "reset",
    "row_independence",
    "segmenter",
    "side_by_side",
    "soak",
    "student",
    "threads",
    "traffic",
    "vae",
)
# The suite, in the order it runs; each writes bench_NAME.json into the suite's folder.
SUITE = ("render", "traffic", "env", "model", "student", "precision", "judge", "first_frame")
DEVICE_BENCHMARKS = ("env", "model", "student")  # the ones that take --device; the others time CPU work


def benchmark_command(name: str, options: list[str]) -> list[str]:
    """The command that runs benchmark ``name`` with ``options`` in a fresh Python process."""
    if name not in BENCHMARKS:
        raise ValueError(f"unknown benchmark {name!r}; choose one of {', '.join(BENCHMARKS)}")
    return [sys.executable, "-m", f"m4world_env.bench.{name}", *options]


def suite_command(name: str, out: Path, evalset: str, device: str) -> list[str]:
    """The command of ``name``'s run in the suite: its default options, the evaluation set where it
    needs one, ``device`` where it takes one, its JSON written to ``out/bench_NAME.json``."""
    options = {
        "render": [],
        "traffic": [],
        "env": ["--backend", "procedural", "world_model"],
        # compiled rows only where inductor can build its kernels (a C++ compiler)
        "model": ["--dtypes", "bf16", "fp32", *(["--compile"] if shutil.which("c++") else [])],
        "student": [],
        "precision": [],  # what dtype auto's fp32/bf16 choice changes in an episode
        "judge": ["--evalset", evalset],
        "first_frame": ["--evalset", evalset, "--cfg", "1", "3", "7"],
    }
    if name not in options:
        raise ValueError(f"{name!r} is not in the suite; choose from {', '.join(SUITE)}")
    chosen = options[name] + (["--device", device] if name in DEVICE_BENCHMARKS else [])
    return benchmark_command(name, [*chosen, "--out", str(out / f"bench_{name}.json")])
