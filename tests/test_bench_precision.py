"""The benchmarks' precision options: m4world bench env's dtype backend spec and m4world bench precision."""

import json

import pytest

from m4world_env.bench.env import make_kwargs
from m4world_env.bench.precision import main as precision_main


def test_bench_env_backend_spec_names_the_world_models_dtype():
    kwargs = make_kwargs
    assert kwargs("world_model", None)["config"] == {"observation_keys": ["cameras", "lidar"]}
    forced = kwargs("world_model:bfloat16", "ckpt", compile_model=True)
    assert forced["backend"] == "world_model" and forced["checkpoint"] == "ckpt"
    assert forced["config"]["model"] == {"compile": True, "dtype": "bfloat16"}
    with pytest.raises(SystemExit, match="only the world_model backend"):
        kwargs("procedural:float32", None)


def test_bench_env_backend_spec_qualifiers_combine():
    kwargs = make_kwargs
    model = kwargs("world_model:float32:compile:no-refresh", None)["config"]["model"]
    assert model == {"dtype": "float32", "compile": True, "context_refresh": False}
    on_gpu = kwargs("world_model", None, device="cuda")["config"]["model"]
    assert on_gpu == {"device": "cuda"}
    with pytest.raises(SystemExit, match="unknown qualifier 'fast'"):
        kwargs("world_model:fast", None)


def test_precision_parity_runs_one_episode_per_dtype(tiny_bundle, tmp_path):
    out = tmp_path / "parity.json"
    precision_main(["--checkpoint", str(tiny_bundle), "--scenario", "merge_cut_in", "--steps", "2", "--out", str(out)])
    result = json.loads(out.read_text())
    assert result["steps"] == 2 and [r["step"] for r in result["per_step"]] == [0, 1, 2]
    # bf16 weights and autocast move the tiny model's cameras: the option reached the env (its untrained
    # LiDAR decodes to the same ranges either way).
    assert result["max_camera_mean_abs_diff_levels"] > 0
    assert result["max_lidar_mean_abs_diff_m"] == max(r["lidar_mean_abs_diff_m"] for r in result["per_step"])
