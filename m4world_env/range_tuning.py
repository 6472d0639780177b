"""A bundle's range head tuned on the env's own rollouts: the LiDAR's close field to the centimetre.

    m4world tune-range-head --out NEW_BUNDLE [--checkpoint BUNDLE] [--seeds 100 101 102 103] \
        [--steps 40] [--train-steps 1000]

The range head (:class:`~world_model.model.range_head.RangeHead`) finishes the decoder's LiDAR view
at the range map's resolution from the range map the scene implies. Its recipe stage learns from
the student's rollouts of the training clips; what it leaves is the close field: a car alongside
drawn a tenth of a metre nearer, where a policy keeping a corridor clear decides by tenths of a
metre (``m4world bench lidar_sectors``, ``close_off``). This tunes the head, every other weight as
it is, on exactly what the env runs:

1. for each of the agreement report's six scenarios and each seed, one episode of the same states
   on both backends (:func:`~m4world_env.same_states.replayed_steps`: ``lane_keeping`` drives the
   ground truth, its actions fed to the world-model env, LiDAR only). At every step the head's own
   inputs (the decoded LiDAR view and the scene's range map, read by a forward pre-hook) are kept
   with the ground truth's range map;
2. the head trains on them with its stage's loss (:func:`~world_model.model.range_head.range_loss`,
   objects weighing :data:`~world_model.train.range_head_stage.OBJECT_WEIGHT`);
3. the new bundle is the old one with the VAE's head replaced and the manifest resealed; its
   ``vae`` entry records the tuning (settings, and the close field's figures before and after on
   the tuning's own frames), written atomically.

The default seeds (100-103) are disjoint from the benchmarks' and the agreement report's (0-15),
which measure the result.
"""

from __future__ import annotations

import copy
import json
import os
import shutil
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from m4world_env.agreement import FULL_SCENARIOS
from m4world_env.same_states import model_env_kwargs, replayed_steps
from world_model.bundle import reseal_bundle, resolve_bundle
from world_model.data.clips import write_json_atomic
from world_model.eval.decisions import BEAM_BANDS, CLOSE_ERROR_M, CLOSE_RANGE_M, lidar_decisions, non_ground_returns
from world_model.model.range_head import RangeHead, range_loss
from world_model.model.vae import image_values_to_ranges, ranges_to_image_values
from world_model.sensors import LidarSpec
from world_model.train.range_head_stage import OBJECT_WEIGHT, RangeExamples

BATCH = 8  # range maps a training step
LEARNING_RATE = 3e-4  # Adam, from the bundle's head (2.9 k weights)
HEAD_PREFIX = "range_head."  # the head's weights in the VAE's state dict
EVAL_BATCH = 32


def collect(checkpoint: str | None, scenarios: Sequence[str], seeds: Sequence[int], steps: int) -> RangeExamples:
    """The head's inputs and the ground truth's range map at every step of every episode (targets in
    float32 image values: a centimetre counts)."""
    frames = []
    for scenario in scenarios:
        for seed in seeds:
            frames += episode_frames(checkpoint, scenario, seed, steps)
            print(f"{scenario} seed {seed}: {len(frames)} frames in all", file=sys.stderr, flush=True)
    if not frames:
        raise ValueError("the episodes gave no frames to tune on: more --steps or other --seeds")
    return RangeExamples(*(torch.cat(x) for x in zip(*frames, strict=True)))


def episode_frames(
    checkpoint: str | None, scenario: str, seed: int, steps: int
) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]:
    """One episode's frames as :func:`collect` keeps them, each (1, ...) tensors: the decoded view,
    the scene's nearness, the ground truth's range map in image values and its object returns. The
    first step is skipped: its view was decoded before the hook could read it."""
    taken: list[tuple[torch.Tensor, torch.Tensor]] = []
    frames, hook = [], None
    try:
        for step in replayed_steps(scenario, seed, steps, model_env_kwargs(("lidar",), checkpoint)):
            if hook is None:
                hook = step.model.backend.wm.vae.range_head.register_forward_pre_hook(lambda _m, a: taken.append(a))
                continue
            (view, near), spec = taken.pop(), step.model.lidar_spec
            if taken or len(view) != 1:
                raise RuntimeError(f"expected one LiDAR view decoded a step, got {len(taken) + len(view)}")
            truth = step.truth_obs["lidar"]
            target = ranges_to_image_values(torch.from_numpy(truth), spec)[None, None]
            objects = torch.from_numpy(non_ground_returns(truth, spec))[None, None]
            frames.append((view.detach().float(), near.detach().clone(), target, objects))
    finally:
        if hook is not None:
            hook.remove()
    return frames


def train(head: RangeHead, examples: RangeExamples, steps: int, seed: int = 0) -> RangeHead:
    """A copy of ``head`` trained ``steps`` steps on ``examples`` (module docstring, step 2)."""
    tuned = copy.deepcopy(head).float().train().requires_grad_(True)
    opt = torch.optim.Adam(tuned.parameters(), lr=LEARNING_RATE)
    rng = np.random.default_rng(seed)
    cpu = torch.device("cpu")
    for _ in range(steps):
        views, nearness, targets, objects = examples.batch(rng.integers(len(examples.views), size=BATCH), cpu)
        loss = range_loss(tuned(views, nearness), targets.float(), objects, OBJECT_WEIGHT)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return tuned.eval().requires_grad_(False)


@torch.no_grad()
def close_field(
    head: RangeHead, examples: RangeExamples, spec: LidarSpec, no_return_fraction: float
) -> dict[str, float | int]:
    """The close field as ``m4world bench lidar_sectors`` reads it (every beam), over ``examples``:
    objects within CLOSE_RANGE_M and the share read more than CLOSE_ERROR_M off."""
    band = BEAM_BANDS[-1]
    close = off = 0
    for s in range(0, len(examples.views), EVAL_BATCH):
        out = head(examples.views[s : s + EVAL_BATCH], examples.nearness[s : s + EVAL_BATCH])
        models = image_values_to_ranges(out[:, 0], spec, no_return_fraction)
        truths = image_values_to_ranges(examples.targets[s : s + EVAL_BATCH, 0].float(), spec, no_return_fraction)
        for truth, model in zip(truths, models, strict=True):
            sums = lidar_decisions(truth, model, spec, (band,)).sectors[band.name]
            close, off = close + sums.close, off + sums.close_off
    return {"close_objects": close, "close_off": off / close if close else float("nan")}


def write_tuned_bundle(source: str | None, out: Path, head: RangeHead, record: dict) -> Path:
    """``source`` (None: the shipped bundle) copied to ``out`` with ``head`` as its VAE's range head
    and ``record`` under the manifest's ``vae`` entry as ``tuned``; written beside ``out`` and moved
    into place whole."""
    src = resolve_bundle(source)
    partial = out.with_name(out.name + ".partial")
    if partial.exists():
        shutil.rmtree(partial)
    shutil.copytree(src, partial)
    vae_file = partial / "vae.safetensors"
    state = load_file(str(vae_file))
    for name, value in head.state_dict().items():
        if HEAD_PREFIX + name not in state:
            raise ValueError(f"{src}'s VAE has no range head to tune ({HEAD_PREFIX + name} missing)")
        state[HEAD_PREFIX + name] = value.float().contiguous()
    save_file(state, str(vae_file))
    manifest_file = partial / "manifest.json"
    manifest = json.loads(manifest_file.read_text())
    manifest["components"]["vae"]["tuned"] = record
    write_json_atomic(manifest_file, manifest)
    reseal_bundle(partial)
    if out.exists():
        shutil.rmtree(out)
    os.replace(partial, out)
    return out


def tune(checkpoint: str | None, out: Path, seeds: Sequence[int], steps: int, train_steps: int) -> dict:
    """The whole job (module docstring); returns what the new bundle's manifest records."""
    from world_model.rollout.runtime import load_world_model

    vae = load_world_model(checkpoint).vae
    if vae.range_head is None:
        raise ValueError(f"{resolve_bundle(checkpoint)}'s VAE has no range head to tune")
    spec, fraction = vae.cfg.sensors.lidar, vae.cfg.vae.lidar_no_return_fraction
    examples = collect(checkpoint, FULL_SCENARIOS, seeds, steps)
    before = close_field(vae.range_head.float().eval(), examples, spec, fraction)
    head = train(vae.range_head, examples, train_steps)
    after = close_field(head, examples, spec, fraction)
    record = {
        "command": "m4world tune-range-head",
        "scenarios": list(FULL_SCENARIOS),
        "seeds": list(seeds),
        "steps": steps,
        "train_steps": train_steps,
        "frames": len(examples.views),
        "close_range_m": CLOSE_RANGE_M,
        "close_error_m": CLOSE_ERROR_M,
        "close_field_before": before,
        "close_field_after": after,
    }
    write_tuned_bundle(checkpoint, out, head, record)
    return record
