"""``--stage lora``: rare/ordinary clip selection, 50/50 balanced sampling, frozen base, export, kill/resume."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.cli_status import exit_status
from tests.model_fixtures import QUIET, kill_after_checkpoint, make_frames, make_sensors, perturbed, tiny_conditions
from world_model.data import Clip, write_clip
from world_model.lora import apply_adapters, base_fingerprint, loaded_adapters, read_adapter, remove_adapters
from world_model.model import MultiViewDiT, SensorVAE, get_preset, make_text_encoder
from world_model.model.reference import ReferenceConfig, object_region
from world_model.train import load_latest, load_teacher, stage_options, train_stage
from world_model.train.checkpoint import export_weights
from world_model.train.data import LatentWindows
from world_model.train.exports import EXPORT
from world_model.train.lora_stage import BalancedSampler, select_clips

CFG = get_preset("tiny")
CASE = "tree_truck"


def _write(root: Path, name: str, n: int, seed: int, rare_from: int | None) -> None:
    """A clip; from frame ``rare_from`` on, object car1 is a tree-hauling truck."""
    frames = make_frames(CFG, n, seed=seed)
    if rare_from is not None:
        frames = [
            fr.with_objects(
                tuple(replace(o, category=CASE) if o.track_id == "car1" and f >= rare_from else o for o in fr.objects)
            )
            for f, fr in enumerate(frames)
        ]
    cams, lidar, bev = make_sensors(CFG, n, phase=0.37 * seed)
    write_clip(root, Clip(name, frames, cams, lidar, bev))


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Base dataset (ordinary clips + one rare clip) and a separate rare-case dataset."""
    root = tmp_path_factory.mktemp("lora")
    base, rare = root / "base", root / "rare"
    for i in range(3):
        _write(base, f"ordinary{i}", 4, i, None)
    _write(base, "rare_in_base", 5, 7, rare_from=2)
    _write(rare, "rare0", 4, 11, rare_from=0)
    _write(rare, "rare1", 3, 12, rare_from=1)
    return base, rare


def train_lora(data, run: Path, steps: int, **kw) -> dict:
    """``--stage lora`` of the tiny preset on the fixture's datasets (rare clips from ``rare``)."""
    base, rare = data
    options = stage_options("lora", preset="tiny", steps=steps, case=CASE, case_data=rare, **kw)
    return train_stage("lora", base, run, options, QUIET)


def lora_argv(data, run: Path) -> list[str]:
    """The train CLIs' arguments of a one-step ``--stage lora`` run on the fixture's datasets."""
    base, rare = data
    argv = ["--stage", "lora", "--case", CASE, "--data", str(base), "--case-data", str(rare), "--run", str(run)]
    return [*argv, "--preset", "tiny", "--no-progress", "--steps", "1"]


def make_run(run: Path) -> Path:
    torch.manual_seed(0)
    meta = {"model_config": CFG.to_dict()}
    export_weights(run / "vae" / EXPORT, perturbed(SensorVAE(CFG), scale=0.05).state_dict(), {"stage": "vae", **meta})
    export_weights(run / "teacher" / EXPORT, perturbed(MultiViewDiT(CFG)).state_dict(), {"stage": "teacher", **meta})
    return run


def test_clip_selection_by_category_dataset_or_list(data):
    base, rare = data
    clips, r, o = select_clips(base, None, CFG, CASE, None)
    assert [clips[i].name for i in r] == ["rare_in_base"] and len(o) == 3
    clips, r, o = select_clips(base, rare, CFG, CASE, None)
    assert sorted(clips[i].name for i in r) == ["rare0", "rare1"]
    assert "rare_in_base" not in {clips[i].name for i in o}  # ordinary clips never hold the rare object
    clips, r, o = select_clips(base, None, CFG, CASE, ["ordinary2"])
    assert [clips[i].name for i in r] == ["ordinary2"] and len(o) == 2
    with pytest.raises(ValueError, match="not in"):
        select_clips(base, None, CFG, CASE, ["missing"])


def test_balanced_sampler_draws_half_rare_half_ordinary(data):
    base, rare = data
    clips, r, o = select_clips(base, rare, CFG, CASE, None)
    lat = [torch.zeros(c.num_frames, *CFG.latent_shape(1)[1:]) for c in clips]
    windows = LatentWindows(clips, lat, CFG, make_text_encoder(CFG.text), None)
    sampler = BalancedSampler(windows, r, o, CASE, 0.5)
    rng = np.random.default_rng(0)
    n, rare_count = 0, 0
    for _ in range(500):
        spans, is_rare = sampler.draw(rng, 4, 2)
        for (ci, start), flag in zip(spans, is_rare, strict=True):
            assert (ci in r) == flag
            if flag:  # rare windows start where the rare object is present
                assert any(ob.category == CASE for ob in clips[ci].frames[start].objects)
        n += len(spans)
        rare_count += int(is_rare.sum())
    assert abs(rare_count / n - 0.5) < 4 * np.sqrt(0.25 / n), rare_count / n
    x0, cond, is_rare, weights, _ = sampler.sample(rng, 3)
    assert x0.shape[0] == 3 and cond.num_frames == x0.shape[1] and weights is None
    with pytest.raises(ValueError, match="no rare-case clips"):
        BalancedSampler(windows, [], o, CASE, 0.5)


def test_box_weights_cover_exactly_the_rare_objects_boxes(data):
    """--lora-box-weight: 1 + w on the latent cells of the rare category's projected boxes (every
    view, LiDAR included, each frame it is in), 1 elsewhere and everywhere in ordinary windows."""
    base, rare = data
    clips, r, o = select_clips(base, rare, CFG, CASE, None)
    lat = [torch.zeros(c.num_frames, *CFG.latent_shape(1)[1:]) for c in clips]
    sampler = BalancedSampler(LatentWindows(clips, lat, CFG, make_text_encoder(CFG.text), None), r, o, CASE, 0.5)
    rare_clip = next(i for i in r if clips[i].name == "rare1")  # car1 is the truck from frame 1 on
    w = sampler.box_weights(rare_clip, 0, 3, 9.0)
    assert w.shape == (3, CFG.sensors.num_views, 1, *CFG.latent_hw)
    assert torch.all(w[0] == 1.0)  # not a truck yet
    exact = ReferenceConfig(margin_px=0)
    for f in (1, 2):
        fr = clips[rare_clip].frames[f]
        region = torch.from_numpy(object_region(fr, "car1", CFG, exact))
        assert region.any() and torch.equal(w[f, :, 0], torch.where(region, 10.0, 1.0))
    assert torch.all(sampler.box_weights(o[0], 0, 2, 9.0) == 1.0)
    x0, _, is_rare, weights, _ = sampler.sample(np.random.default_rng(1), 8, box_weight=9.0)
    assert weights.shape == (*x0.shape[:3], 1, *x0.shape[4:])
    assert torch.all(weights[torch.from_numpy(~is_rare)] == 1.0) and weights.max() == 10.0


def test_a_reference_model_base_learns_to_complete_the_rare_object(data, tmp_path):
    """Reference-model base: rare windows observe all but the rare objects' regions (object
    completion of the case), ordinary ones get the reference stage's task mix; the adapter trains."""
    from world_model.model.reference import category_region, expand_teacher

    base, rare = data
    clips, r, o = select_clips(base, rare, CFG, CASE, None)
    lat = [torch.zeros(c.num_frames, *CFG.latent_shape(1)[1:]) for c in clips]
    sampler = BalancedSampler(LatentWindows(clips, lat, CFG, make_text_encoder(CFG.text), None), r, o, CASE, 0.5)
    rcfg = ReferenceConfig()
    rng = np.random.default_rng(0)
    seen_rare = seen_ordinary = 0
    for _ in range(10):
        batch = sampler.sample(rng, 4)
        masks = sampler.reference_masks(rng, batch, rcfg)
        assert masks.shape == (*batch.x0.shape[:3], 1, *batch.x0.shape[4:])
        for (ci, s), is_rare, m in zip(batch.spans, batch.is_rare, masks, strict=True):
            if is_rare:
                region = category_region(clips[ci].frames[s : s + m.shape[0]], CASE, CFG, rcfg)
                assert region.any() and torch.equal(m[:, :, 0], torch.from_numpy(~region).float())
                seen_rare += 1
            else:
                assert set(m.unique().tolist()) <= {0.0, 1.0}
                seen_ordinary += 1
    assert seen_rare and seen_ordinary

    run = make_run(tmp_path / "run")
    reference = expand_teacher(load_teacher(run / "teacher" / EXPORT))
    meta = {"stage": "reference", "model_config": reference.cfg.to_dict()}
    export_weights(run / "reference" / EXPORT, perturbed(reference).state_dict(), meta)
    out = train_lora(data, run, 2, base=run / "reference" / EXPORT)
    info, tensors = read_adapter(Path(out["adapter_dir"]))
    assert info.meta["model_config"]["dit"]["in_channels_extra"] == CFG.vae.latent_channels + 1
    assert info.meta["train"]["reference_tasks"] is True
    assert any(not torch.all(v == 0) for k, v in tensors.items() if "lora_B" in k)


def test_lora_box_weight_is_validated_recorded_and_fixed_for_a_run(data, tmp_path, capsys):
    from m4world_env.cli import main as m4world
    from world_model.train.__main__ import main

    run = make_run(tmp_path / "run")
    argv = lora_argv(data, run)
    assert exit_status(main, [*argv, "--lora-box-weight", "-1"]) == 2
    assert exit_status(m4world, ["train", *argv, "--lora-box-weight", "nan"]) == 2
    assert exit_status(main, [*argv, "--lora-box-weight", "inf"]) == 2
    assert capsys.readouterr().err.count("argument --lora-box-weight: must be a finite number of at least 0") == 3
    assert not (run / "lora").exists()
    teacher_argv = ["--stage", "teacher", *argv[2:]]
    assert exit_status(m4world, ["train", *teacher_argv, "--lora-box-weight", "9"]) == 2
    assert "setting of --stage lora" in capsys.readouterr().err
    assert main([*argv, "--lora-box-weight", "4"]) == 0
    info, _ = read_adapter(run / "lora" / CASE)
    assert info.meta["train"]["box_weight"] == 4.0
    with pytest.raises(ValueError, match="box_weight=4.0"):  # resuming with another objective
        train_lora(data, run, 2)
    other = run / "other_teacher" / EXPORT
    export_weights(
        other, perturbed(load_teacher(run / "teacher" / EXPORT)).state_dict(), {"model_config": CFG.to_dict()}
    )
    with pytest.raises(ValueError, match="base_sha256"):  # resuming on another base model
        train_lora(data, run, 2, base=other, box_weight=4.0)


def test_the_stage_feeds_box_weights_and_completion_masks_to_the_loss(data, tmp_path, monkeypatch):
    """Wiring: the weights reach the flow loss, and a reference base gets completion masks (not
    the all-zero reference of a controls-only objective)."""
    from world_model.model.reference import expand_teacher
    from world_model.train import lora_stage

    seen = {"weights": [], "masks": []}
    loss_fn, ref_fn = lora_stage.flow_matching_loss, lora_stage.reference_input

    def loss(fn, x0, t, noise, weights=None):
        seen["weights"].append(weights)
        return loss_fn(fn, x0, t, noise, weights)

    def reference(latents, mask):
        seen["masks"].append(mask)
        return ref_fn(latents, mask)

    monkeypatch.setattr(lora_stage, "flow_matching_loss", loss)
    monkeypatch.setattr(lora_stage, "reference_input", reference)
    run = make_run(tmp_path / "run")
    reference_model = expand_teacher(load_teacher(run / "teacher" / EXPORT))
    export_weights(
        run / "reference" / EXPORT,
        perturbed(reference_model).state_dict(),
        {"model_config": reference_model.cfg.to_dict()},
    )
    train_lora(data, run, 6, base=run / "reference" / EXPORT, box_weight=9.0)
    assert len(seen["weights"]) == 6 and all(w is not None and w.min() == 1.0 for w in seen["weights"])
    assert max(float(w.max()) for w in seen["weights"]) == 10.0
    masks = torch.cat([m.flatten() for m in seen["masks"]])
    assert len(seen["masks"]) == 6 and masks.min() == 0.0 and masks.max() == 1.0


def test_lora_stage_trains_only_the_adapter_and_exports_it(data, tmp_path):
    base, rare = data
    run = make_run(tmp_path / "run")
    out = train_lora(data, run, 3, ckpt_every=1)
    assert out["step"] == 3 and out["drawn"]["rare"] + out["drawn"]["ordinary"] == 3 * 4
    teacher = load_teacher(run / "teacher" / EXPORT)
    info, tensors = read_adapter(run / "lora" / CASE)
    assert info.base_sha256 == base_fingerprint(teacher) and all(".lora_" in k for k in tensors)
    assert sorted(info.meta["train"]["rare_clips"]) == ["rare0", "rare1"]
    # The frozen base inside the training checkpoint is bit-identical to the teacher export.
    state = load_latest(run / "lora" / CASE / "checkpoints").tensors["model"]
    base_state = {k.replace(".base_layer.", "."): v for k, v in state.items() if ".lora_" not in k}
    ref = teacher.state_dict()
    assert base_state.keys() == ref.keys() and all(torch.equal(base_state[k], ref[k]) for k in ref)
    assert any(not torch.all(v == 0) for k, v in tensors.items() if "lora_B" in k)  # the adapter learned
    cond = tiny_conditions(CFG, 2)
    x = torch.randn(1, *CFG.latent_shape(2), generator=torch.Generator().manual_seed(0))
    t = torch.tensor([0.5])
    with torch.no_grad():
        y0 = teacher(x, t, cond)
        apply_adapters(teacher, [CASE], search_dirs=[run / "lora"])
        assert not torch.equal(teacher(x, t, cond), y0)
        remove_adapters(teacher)
        assert torch.equal(teacher(x, t, cond), y0)


def test_lora_stage_errors_are_actionable(data, tmp_path):
    base, _ = data
    with pytest.raises(ValueError, match="needs --case"):
        train_stage("lora", base, tmp_path / "r", stage_options("lora", preset="tiny", steps=1), QUIET)
    with pytest.raises(FileNotFoundError, match="run --stage teacher first"):
        train_stage("lora", base, tmp_path / "r", stage_options("lora", preset="tiny", steps=1, case=CASE), QUIET)
    with pytest.raises(ValueError, match="no rare-case clips"):
        train_stage(
            "lora", base, make_run(tmp_path / "r2"), stage_options("lora", preset="tiny", steps=1, case="bus"), QUIET
        )


def test_killed_lora_run_resumes_from_last_checkpoint(data, tmp_path):
    base, rare = data
    run = make_run(tmp_path / "run")
    args = ["--stage", "lora", "--case", CASE, "--data", str(base), "--case-data", str(rare), "--run", str(run)]
    latest = run / "lora" / CASE / "checkpoints" / "latest.json"
    kill_after_checkpoint(
        [*args, "--preset", "tiny", "--steps", "100000", "--ckpt-every", "2", "--no-progress"], latest.parent
    )
    ck = load_latest(latest.parent)
    assert ck is not None and ck.step >= 4
    out = train_lora(data, run, ck.step + 2, ckpt_every=2)
    assert out["resumed_from"] == ck.step and out["step"] == ck.step + 2
    assert (run / "lora" / CASE / "adapter.safetensors").exists()


def test_lora_adapts_a_shallower_student_and_refuses_another_family(data, tmp_path):
    base, rare = data
    run = make_run(tmp_path / "run")
    student_cfg = replace(CFG.with_depth(1), clip=replace(CFG.clip, context_frames=CFG.clip.context_frames + 1))
    meta = {"stage": "long", "model_config": student_cfg.to_dict()}
    export_weights(run / "long" / EXPORT, perturbed(MultiViewDiT(student_cfg)).state_dict(), meta)
    out = train_lora(data, run, 1, base=run / "long" / EXPORT)
    assert read_adapter(Path(out["adapter_dir"]))[0].meta["model_config"]["dit"]["depth"] == 1

    other = replace(CFG, sensors=replace(CFG.sensors, width=CFG.sensors.width * 2))
    export_weights(run / "other" / EXPORT, MultiViewDiT(other).state_dict(), {"model_config": other.to_dict()})
    with pytest.raises(ValueError, match="has preset"):
        train_lora(data, run, 1, base=run / "other" / EXPORT)


def test_lora_adapts_a_checkpoint_bundle_without_a_training_run(data, tmp_path):
    """``--base BUNDLE``: the bundle's student in the bundle's VAE latents; the adapter then loads
    onto the model the env serves from that bundle."""
    from world_model.rollout.runtime import load_world_model, save_untrained_bundle

    base, rare = data
    bundle = save_untrained_bundle(tmp_path / "bundle", preset="tiny", seed=3)
    run = tmp_path / "run"  # empty: no vae/ or teacher/
    out = train_lora(data, run, 2, base=bundle)
    assert out["step"] == 2 and not (run / "vae").exists()
    info, _ = read_adapter(Path(out["adapter_dir"]))
    wm = load_world_model(bundle)
    assert info.base_sha256 == base_fingerprint(wm.student)
    assert info.meta["base_file"] == "student.safetensors"
    cached = sorted(p.name for p in (run / "teacher" / "latents").glob("*.safetensors"))
    assert "rare0.safetensors" in cached and "ordinary0.safetensors" in cached
    assert apply_adapters(wm.student, [CASE], search_dirs=[run / "lora"]) == [CASE]
    # Another bundle's student is another base: its adapter is refused there.
    other = load_world_model(save_untrained_bundle(tmp_path / "other", preset="tiny", seed=4))
    with pytest.raises(ValueError, match="base"):
        apply_adapters(other.student, [CASE], search_dirs=[run / "lora"])
    # BUNDLE/reference.safetensors: the bundle's reference model, trained in its completion tasks.
    out = train_lora(data, tmp_path / "ref_run", 1, base=bundle / "reference.safetensors")
    info, _ = read_adapter(Path(out["adapter_dir"]))
    assert info.base_sha256 == base_fingerprint(wm.reference) and info.meta["train"]["reference_tasks"] is True
    assert info.meta["base_file"] == "reference.safetensors"
    wm.apply_adapters([out["adapter_dir"]])
    assert loaded_adapters(wm.reference) == [CASE]


def test_a_bundle_loaded_in_float32_is_still_the_presets_family(tmp_path):
    """Loading rewrites ``dit.autocast_bf16`` per machine: the family check must not see it."""
    from world_model.rollout.runtime import save_untrained_bundle
    from world_model.train.lora_stage import load_lora_base

    cfg = replace(CFG, dit=replace(CFG.dit, autocast_bf16=True))
    bundle = save_untrained_bundle(tmp_path / "b", preset="tiny")
    assert load_lora_base(bundle, tmp_path / "run", cfg).model.cfg.dit.autocast_bf16 is False


def test_lora_rank_is_validated_recorded_and_fixed_for_a_run(data, tmp_path, capsys):
    """--lora-rank: the adapter's shapes and recorded config follow it (update scale kept at the
    default's alpha / rank); a bad rank or another stage is refused before anything is written, and
    a run resumes only at the rank it started with."""
    from m4world_env.cli import main as m4world
    from world_model.lora import LoraConfig
    from world_model.train.__main__ import main

    run = make_run(tmp_path / "run")
    argv = lora_argv(data, run)
    assert exit_status(main, [*argv, "--lora-rank", "0"]) == 2
    assert exit_status(m4world, ["train", *argv, "--lora-rank", "-3"]) == 2
    assert capsys.readouterr().err.count("argument --lora-rank: must be a positive integer") == 2
    assert not (run / "lora").exists()
    assert exit_status(m4world, ["train", "--stage", "teacher", *argv[2:], "--lora-rank", "4"]) == 2
    assert "--lora-rank is a setting of --stage lora" in capsys.readouterr().err
    assert main([*argv, "--lora-rank", "4"]) == 0
    info, tensors = read_adapter(run / "lora" / CASE)
    default = LoraConfig()
    assert info.lora.rank == 4 and info.lora.alpha / 4 == default.alpha / default.rank
    down = [v for k, v in tensors.items() if "lora_A" in k]
    assert down and all(v.shape[0] == 4 for v in down)
    with pytest.raises(ValueError, match="lora_rank=4"):  # resumed at the default rank
        train_lora(data, run, 2)


def test_a_reference_base_run_from_before_the_completion_objective_is_not_resumed(data, tmp_path):
    """A checkpoint whose meta predates ``reference_tasks`` was trained controls-only: resuming it
    under the completion objective would mix two objectives in one adapter."""
    from world_model.model.reference import expand_teacher

    run = make_run(tmp_path / "run")
    reference = expand_teacher(load_teacher(run / "teacher" / EXPORT))
    export_weights(
        run / "reference" / EXPORT, perturbed(reference).state_dict(), {"model_config": reference.cfg.to_dict()}
    )
    train_lora(data, run, 1, base=run / "reference" / EXPORT)
    ckpts = run / "lora" / CASE / "checkpoints"
    meta_file = ckpts / json.loads((ckpts / "latest.json").read_text())["dir"] / "meta.json"
    meta = json.loads(meta_file.read_text())
    assert meta.pop("reference_tasks") is True
    meta_file.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="reference_tasks=False"):
        train_lora(data, run, 2, base=run / "reference" / EXPORT)
