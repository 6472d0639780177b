"""m4world bench student end to end on the tiny preset (random weights): sections and ratios."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]  # the subprocess's cwd: it imports this checkout's packages


def test_bench_student_times_every_engine_and_the_rollout(tmp_path):
    out = tmp_path / "student.json"
    cmd = [sys.executable, "-m", "m4world_env.bench.student", "--preset", "tiny", "--envs", "2"]
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


def test_the_recompute_baseline_is_the_computation_the_cache_replaces():
    """bench_student's RecomputeWindow (every step re-runs the window) and the engine's KV cache
    give the same chunks from the same noise while the window holds the whole rollout (once frames
    leave it, the cache keeps keys computed with the older context: the approximation it makes)."""
    import dataclasses

    import torch

    from m4world_env.bench.student import RecomputeWindow
    from tests.model_fixtures import perturbed, tiny_conditions
    from world_model.model import MultiViewDiT, get_preset
    from world_model.student import StreamingEngine, StudentConfig
    from world_model.student.config import TRAINING_STREAMING

    chunks, c = 3, 1
    cfg = get_preset("tiny").for_student()
    cfg = dataclasses.replace(cfg, clip=dataclasses.replace(cfg.clip, chunk_frames=c, context_frames=1 + chunks * c))
    torch.manual_seed(0)
    model = perturbed(MultiViewDiT(cfg))
    cond = tiny_conditions(cfg, 1 + chunks * c, batch=2)
    first = torch.randn(2, *cfg.latent_shape(1), generator=torch.Generator().manual_seed(3))
    scfg = StudentConfig(streaming=dataclasses.replace(TRAINING_STREAMING, context_refresh=False))
    outs = []
    for engine in (StreamingEngine, RecomputeWindow):
        eng = engine(model, scfg, torch.Generator().manual_seed(1))
        with torch.no_grad():
            eng.start(first, cond.frames(0, 1))
            outs.append(torch.cat([eng.step(cond.frames(1 + k * c, 1 + (k + 1) * c)) for k in range(chunks)], 1))
    assert outs[0].abs().mean() > 0.1
    assert (outs[0] - outs[1]).abs().max().item() <= 1e-4
