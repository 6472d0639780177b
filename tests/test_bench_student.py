"""benchmarks/bench_student.py end to end on the tiny preset (random weights): sections and ratios."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_bench_student_times_every_engine_and_the_rollout(tmp_path):
    out = tmp_path / "student.json"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "bench_student.py"), "--preset", "tiny", "--envs", "2"]
    cmd += ["--frames", "24", "--repeats", "2", "--sections", "cache_vs_recompute", "rollout", "--out", str(out)]
    subprocess.run(cmd, check=True, cwd=ROOT, capture_output=True)
    result = json.loads(out.read_text())
    timed = result["cache_vs_recompute"]
    engines = ("cached_refresh", "cached_refresh_late", "cached_no_refresh")
    for name in engines:
        assert len(timed[f"{name}_rounds_s"]) == 2
        assert timed[f"recompute_over_{name}"] == timed["recompute_chunk_s"] / timed[f"{name}_chunk_s"] > 0
    assert timed["window"] == result["model_config"]["clip"]["context_frames"]
    assert result["rollout"]["frames"] >= 24 - result["model_config"]["clip"]["chunk_frames"]
