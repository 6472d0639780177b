"""Training on a chosen device and on several processes: --device, batched windows, torchrun (gloo)."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from tests.model_fixtures import make_dataset
from world_model.model import get_preset
from world_model.model.conditions import Conditions
from world_model.model.text import make_text_encoder
from world_model.train import StageRuntime, load_latest, stage_options, train_stage
from world_model.train.data import LatentWindows, load_clips
from world_model.train.device import TrainPlace, resolve_device

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def vae_run(tmp_path_factory):
    """A tiny dataset and a run with a trained VAE (what every later stage starts from)."""
    root = tmp_path_factory.mktemp("device")
    data = make_dataset(root / "data", get_preset("tiny"), lengths=(6, 5, 4))
    train_stage(
        "vae",
        data,
        root / "run",
        stage_options("vae", preset="tiny", steps=2),
        StageRuntime(progress=False, device="cpu"),
    )
    return data, root / "run"


def test_device_option_resolves_or_says_what_is_missing():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ValueError, match="--device must be auto, cpu, cuda or cuda:N"):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        for spec in ("cuda", "cuda:1"):
            with pytest.raises(ValueError, match=f"--device {spec}: no CUDA GPU is available"):
                resolve_device(spec)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error on a machine without CUDA")
def test_train_cli_with_device_cuda_without_cuda_is_a_clear_error(vae_run, tmp_path, capsys):
    from m4world_env.cli import main as m4world
    from world_model.train.cli import main

    data, _ = vae_run
    args = ["--stage", "vae", "--data", str(data), "--run", str(tmp_path / "r"), "--preset", "tiny", "--steps", "1"]
    assert main([*args, "--device", "cuda"]) == 2
    assert m4world(["train", *args, "--device", "cuda:0"]) == 2
    err = capsys.readouterr().err
    assert err.count("no CUDA GPU is available") == 2 and "--device cpu" in err
    assert not (tmp_path / "r" / "vae" / "checkpoints").exists()


def test_batched_windows_equal_the_per_sample_windows(vae_run):
    data, _ = vae_run
    cfg = get_preset("tiny")
    clips = load_clips(data, cfg)
    gen = torch.Generator().manual_seed(0)
    latents = [torch.randn(c.num_frames, *cfg.latent_shape(1)[1:], generator=gen) for c in clips]
    windows = LatentWindows(clips, latents, cfg, make_text_encoder(cfg.text), None)
    picks, starts = np.array([2, 0, 1, 0]), np.array([1, 2, 0, 0])
    x0, cond = windows.windows(picks, starts, 3)
    items = [windows.window(int(c), int(s), 3) for c, s in zip(picks, starts, strict=True)]
    want = Conditions.collate([a for _, a in items])
    assert torch.equal(x0, torch.stack([x for x, _ in items]).float())
    for name in want.__dataclass_fields__:
        got, expected = getattr(cond, name), getattr(want, name)
        assert torch.allclose(got, expected, atol=1e-5) if got.is_floating_point() else torch.equal(got, expected)


def test_a_shard_takes_the_ranks_rows_of_the_global_batch():
    x = torch.arange(8)
    assert TrainPlace(torch.device("cpu"), rank=1, world_size=2).shard(x).tolist() == [4, 5, 6, 7]
    assert TrainPlace(torch.device("cpu")).shard(x).tolist() == list(range(8))
    with pytest.raises(ValueError, match="batch size \\(3\\) must be a multiple of the number of processes \\(2\\)"):
        TrainPlace(torch.device("cpu"), rank=0, world_size=2).shard(torch.arange(3))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _train(data: Path, run: Path, stage: str, nproc: int, steps: int) -> dict:
    """``--stage STAGE``: in this process when ``nproc`` is 1, else through the training CLI under
    ``torchrun --nproc-per-node nproc``."""
    if nproc == 1:
        return train_stage(
            stage,
            data,
            run,
            stage_options(stage, preset="tiny", steps=steps, batch_size=4, ckpt_every=1),
            StageRuntime(progress=False, device="cpu"),
        )
    args = ["--stage", stage, "--data", str(data), "--run", str(run), "--preset", "tiny", "--no-progress"]
    args += ["--steps", str(steps), "--batch-size", "4", "--ckpt-every", "1", "--device", "cpu"]
    launch = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", str(nproc)]
    launch += ["--master-port", str(_free_port()), "-m", "world_model.train", "--"]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    done = subprocess.run([*launch, *args], capture_output=True, text=True, env=env, timeout=120, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout[done.stdout.index("{") :])


@pytest.fixture(scope="module")
def chain_run(vae_run, tmp_path_factory):
    """The run of ``vae_run`` trained one step further through teacher, tf and ode (in a copy).
    tf and ode train like the teacher here (a shard of each drawn tensor); dmd adds rollouts and
    the critic's own updates."""
    data, vae = vae_run
    run = tmp_path_factory.mktemp("chain") / "run"
    shutil.copytree(vae, run)
    for stage in ("teacher", "tf", "ode"):
        train_stage(
            stage,
            data,
            run,
            stage_options(stage, preset="tiny", steps=1, batch_size=2),
            StageRuntime(progress=False, device="cpu"),
        )
    return data, run


@pytest.mark.parametrize("stage, steps", [("teacher", 3), ("dmd", 2)])
def test_two_gloo_processes_train_as_one_process_at_the_same_global_batch(chain_run, tmp_path, stage, steps):
    """Each rank trains its half of the global batch and averages gradients: the same losses and
    weights as one process (dmd: critic and generator updates, rollouts split over the ranks)."""
    data, prepared = chain_run
    runs = {}
    for nproc in (1, 2):
        run = tmp_path / f"n{nproc}"
        shutil.copytree(prepared, run)
        shutil.rmtree(run / stage, ignore_errors=True)
        runs[nproc] = (run, _train(data, run, stage, nproc, steps))
    (one, s1), (two, s2) = runs[1], runs[2]
    assert s1["step"] == s2["step"] == steps
    assert s2["final_loss"] == pytest.approx(s1["final_loss"], rel=1e-5)
    ck1, ck2 = load_latest(one / stage / "checkpoints"), load_latest(two / stage / "checkpoints")
    assert ck2.meta["loss"] == pytest.approx(ck1.meta["loss"], rel=1e-5)
    for name, w in ck1.tensors["model"].items():
        assert torch.allclose(ck2.tensors["model"][name], w, atol=1e-5), name
    e1, e2 = load_file(str(one / stage / "model.safetensors")), load_file(str(two / stage / "model.safetensors"))
    assert e1.keys() == e2.keys() and all(torch.allclose(e1[k], e2[k], atol=1e-5) for k in e1)
    # rank 0 alone writes: one progress file, one set of checkpoints
    kept = sorted(p.name for p in (two / stage / "checkpoints").iterdir())
    assert kept == ["latest.json", f"step_{steps - 1:08d}", f"step_{steps:08d}"]


def test_condition_dropout_masks_live_on_the_conditions_device():
    """Training's guided ODE targets (ode stage) and DMD's real score drop conditions of batches
    already on the training device; the mask must be created there (the meta device stands in for a GPU)."""
    from tests.model_fixtures import tiny_conditions

    cond = tiny_conditions(get_preset("tiny"), 2, batch=2).to("meta")
    assert cond.with_drop(True).drop.device.type == "meta"
    assert Conditions.cat([cond, cond.with_drop(True)]).drop.shape == (4,)
