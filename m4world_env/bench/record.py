"""Recording speed: ``m4world record`` serial vs ``--workers N``, interleaved rounds, same clips.

Each round records the same clips (``--clips`` episodes of ``--scenario``, ``--duration`` s each,
the default preset's sensors) into fresh folders, once per worker count, in a fresh process each
(as the command runs); the report gives each worker count's median wall time and the median over
rounds of the per-round speed-up against one worker. A machine shared with other jobs slows all
rows of a round alike, so a within-round ratio is the honest figure.

    m4world bench record --workers 1 2 --clips 8 --duration 5 --rounds 3 --out F.json
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def record_once(workers: int, args: argparse.Namespace, out: Path) -> float:
    """Wall seconds of one ``m4world record`` run in a fresh process."""
    cmd = [sys.executable, "-m", "m4world_env.cli", "record", "--scenario", args.scenario, "--out", str(out)]
    cmd += ["--episodes", str(args.clips), "--duration", str(args.duration), "--workers", str(workers)]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True)
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="m4world bench record", description=__doc__.split("\n\n")[0])
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker counts; the first is the baseline")
    p.add_argument("--clips", type=int, default=8)
    p.add_argument("--duration", type=float, default=5.0, help="seconds per clip")
    p.add_argument("--scenario", default="highway_sunny_day")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--out", type=Path, required=True)
    a = p.parse_args(argv)
    rounds: list[dict[int, float]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(a.rounds):
            order = a.workers if r % 2 == 0 else a.workers[::-1]  # alternate who runs first
            times = {}
            for w in order:
                out = Path(tmp) / f"round{r}_workers{w}"
                times[w] = record_once(w, a, out)
                shutil.rmtree(out)
            rounds.append(times)
            print(json.dumps({"round": r, "seconds": times}), flush=True)
    base = a.workers[0]
    result = {
        "scenario": a.scenario,
        "clips": a.clips,
        "duration_s": a.duration,
        "cpus": os.cpu_count(),
        "load_average_1min_at_end": os.getloadavg()[0],
        "median_s": {w: statistics.median(t[w] for t in rounds) for w in a.workers},
        "speedup_vs_first": {w: statistics.median(t[base] / t[w] for t in rounds) for w in a.workers},
        "per_round_s": rounds,
    }
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(result, indent=1))
    print(json.dumps({k: v for k, v in result.items() if k != "per_round_s"}, indent=1))


if __name__ == "__main__":
    main()
