"""The env on the world-model backend (untrained tiny bundle: plumbing, seeding, errors)."""

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.error import ResetNeeded
from gymnasium.utils.env_checker import check_env

import m4world_env  # noqa: F401
from m4world_env.config import InvalidOptionError
from m4world_env.env import M4WorldEnv
from world_model.bundle import CheckpointError, CheckpointNotFoundError
from world_model.rollout.runtime import load_world_model
from world_model.streaming import StreamingConfig

from .model_fixtures import perturbed

KEYS = {"observation_keys": ["cameras", "lidar", "bev", "state"]}


def test_check_env_world_model_backend(tiny_bundle):
    env = M4WorldEnv("merge_cut_in", backend="world_model", checkpoint=str(tiny_bundle), config=KEYS)
    check_env(env, skip_render_check=True)
    obs, _ = env.reset(seed=0)
    cfg = env.backend.wm.cfg
    assert obs["cameras"].shape == (6, cfg.sensors.height, cfg.sensors.width, 3)
    assert obs["lidar"].shape == (32, 1024) and obs["lidar"].dtype == np.float32
    assert env.observation_space.contains(obs)
    assert env.rig.resolution == (cfg.sensors.height, cfg.sensors.width)  # the checkpoint's sensors


def test_world_model_same_seed_same_observations(tiny_bundle):
    def run(seed):
        env = M4WorldEnv("merge_cut_in", backend="world_model", checkpoint=str(tiny_bundle), config=KEYS)
        out = [env.reset(seed=seed)[0]]
        for a in ([0.3, 0.0], [0.0, 0.1]):
            out.append(env.step(np.array(a, np.float32))[0])
        return out

    a, b, c = run(3), run(3), run(4)
    for oa, ob in zip(a, b, strict=True):
        for k in oa:
            assert np.array_equal(oa[k], ob[k]), k
    assert not np.array_equal(a[-1]["cameras"], c[-1]["cameras"])


def test_rgb_array_list_decodes_and_renders_every_generated_frame(active_bundle):
    """Each step's chunk has two frames: both are decoded and rendered, the newest as in rgb_array."""
    every = M4WorldEnv("merge_cut_in", "world_model", str(active_bundle), "rgb_array_list", KEYS)
    single = M4WorldEnv("merge_cut_in", "world_model", str(active_bundle), "rgb_array", KEYS)
    every.reset(seed=1)
    single.reset(seed=1)
    assert np.array_equal(every.render()[0], single.render())
    for env in (every, single):
        env.step(np.array([0.3, 0.0], np.float32))
    older, newest = every.render()
    assert np.abs(newest.astype(int) - single.render()).max() <= 1  # decoded in a batch of 2 vs 1
    assert not np.array_equal(older, newest)


LIDAR_ATOL_M = 0.01  # batched vs batch-of-one LiDAR: measured ~3e-5 m apart


def test_a_second_reset_with_the_same_seed_repeats_the_episode_exactly(active_bundle):
    env = M4WorldEnv("merge_cut_in", backend="world_model", checkpoint=str(active_bundle), config=KEYS)

    def episode() -> list[dict]:
        out = [env.reset(seed=3)[0]]
        for a in ([0.3, 0.0], [0.0, 0.1], [-0.2, 0.0]):
            out.append(env.step(np.array(a, np.float32))[0])
        return out

    first, again = episode(), episode()
    for step, (oa, ob) in enumerate(zip(first, again, strict=True)):
        for k in oa:
            assert np.array_equal(oa[k], ob[k]), (step, k)


def assert_rows_equal_singles(vobs: dict, sobs: list[dict], step: int) -> None:
    """Vector-env row i equals single env i: one batched forward vs N batch-of-one forwards are
    equal up to float summation order."""
    for i, single in enumerate(sobs):
        diff = np.abs(vobs["cameras"][i].astype(int) - single["cameras"].astype(int))
        assert diff.max() <= 2 and diff.mean() < 0.05, (step, i)
        assert np.allclose(vobs["lidar"][i], single["lidar"], atol=LIDAR_ATOL_M), (step, i)


def _wm_env(scenario, bundle, cfg) -> M4WorldEnv:
    return M4WorldEnv(scenario, backend="world_model", checkpoint=str(bundle), config=cfg)


def _wm_vector(scenario, bundle, cfg, n):
    return gym.make_vec(
        "M4World-v0",
        num_envs=n,
        vectorization_mode="vector_entry_point",
        scenario=scenario,
        backend="world_model",
        checkpoint=str(bundle),
        config=cfg,
    )


def test_world_model_vector_env_equals_single_envs(active_bundle):
    """Each row gets its own actions; on a bundle whose output depends on its controls, swapped or
    shared rows would show: the rows differ, and a single env fed another row's actions does not
    reproduce that row."""
    n, seed = 3, 5
    cfg = {"observation_keys": ["cameras", "lidar"]}
    venv = _wm_vector("merge_cut_in", active_bundle, cfg, n)
    singles = [_wm_env("merge_cut_in", active_bundle, cfg) for _ in range(n)]
    swapped = _wm_env("merge_cut_in", active_bundle, cfg)  # row 0's seed, row 1's actions
    vobs, _ = venv.reset(seed=seed)
    sobs = [env.reset(seed=seed + i)[0] for i, env in enumerate(singles)]
    swapped.reset(seed=seed)
    actions = np.array([[1.0, 0.05], [-1.0, -0.05], [0.0, 0.0]], np.float32)
    assert_rows_equal_singles(vobs, sobs, 0)
    for step in range(1, 4):
        vobs = venv.step(actions)[0]
        sobs = [env.step(a)[0] for env, a in zip(singles, actions, strict=True)]
        other = swapped.step(actions[1])[0]
        assert_rows_equal_singles(vobs, sobs, step)
    assert np.abs(vobs["lidar"][0] - vobs["lidar"][1]).max() > 10 * LIDAR_ATOL_M
    assert np.abs(other["lidar"] - vobs["lidar"][0]).max() > 10 * LIDAR_ATOL_M  # the actions reached the model


def test_world_model_vector_env_autoreset_equals_a_single_env_reset(active_bundle):
    """A row whose episode ended is reset at the next step (AutoresetMode.NEXT_STEP) exactly as a
    single env's ``reset()`` without a seed, and both continue alike while the other rows go on."""
    from m4world_env.scenario import load_scenario

    n, seed = 2, 7
    cfg = {"observation_keys": ["cameras", "lidar"]}
    short = load_scenario("merge_cut_in").model_copy(update={"duration": 1.0})
    venv = _wm_vector(short, active_bundle, cfg, n)
    assert venv.metadata["autoreset_mode"] == gym.vector.AutoresetMode.NEXT_STEP
    singles = [_wm_env(short, active_bundle, cfg) for _ in range(n)]
    venv.reset(seed=seed)
    for i, env in enumerate(singles):
        env.reset(seed=seed + i)
    actions = np.array([[0.5, 0.0], [-0.5, 0.2]], np.float32)
    ended = np.zeros(n, bool)
    resets = 0
    for step in range(12):
        vobs, rew, term, trunc, _ = venv.step(actions)
        sobs = []
        for i, env in enumerate(singles):
            if ended[i]:
                sobs.append(env.reset()[0])
                assert rew[i] == 0.0 and not term[i] and not trunc[i]
                resets += 1
            else:
                sobs.append(env.step(actions[i])[0])
        assert_rows_equal_singles(vobs, sobs, step)
        ended = term | trunc
    assert resets >= 2  # an episode is 5 steps: every row was reset at least once and continued


def test_reset_with_reference_image_and_bad_references(tiny_bundle):
    env = M4WorldEnv("merge_cut_in", backend="world_model", checkpoint=str(tiny_bundle), config=KEYS)
    h, w = env.rig.resolution
    front = np.full((h, w, 3), 200, np.uint8)
    obs, _ = env.reset(seed=0, options={"reference": {"FRONT": front}})
    assert obs["cameras"].shape[1:3] == (h, w)
    with pytest.raises(ValueError, match="FRONT.*resize"):
        env.reset(seed=0, options={"reference": {"FRONT": np.zeros((h + 1, w, 3), np.uint8)}})
    with pytest.raises(ValueError, match="channels last"):
        env.reset(seed=0, options={"reference": {"FRONT": np.zeros((3, h, w), np.uint8)}})
    with pytest.raises(TypeError, match="must be a dict"):
        env.reset(seed=0, options={"reference": [front]})
    with pytest.raises(ResetNeeded, match="last reset failed"):  # no half-reset episode to step on
        env.step(np.zeros(2, np.float32))
    env.reset(seed=0)  # still usable
    env.step(np.zeros(2, np.float32))


def test_missing_or_corrupt_checkpoint_is_a_clear_error(tiny_bundle, tmp_path):
    with pytest.raises(CheckpointNotFoundError, match="does not exist"):
        M4WorldEnv("merge_cut_in", backend="world_model", checkpoint=str(tmp_path / "none"))
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(tiny_bundle, broken)
    (broken / "vae.safetensors").write_bytes(b"garbage")
    with pytest.raises(CheckpointError, match="vae.safetensors is corrupt"):
        M4WorldEnv("merge_cut_in", backend="world_model", checkpoint=str(broken))
    with pytest.raises(CheckpointError, match="is a file"):
        M4WorldEnv("merge_cut_in", backend="world_model", checkpoint=str(tiny_bundle / "student.safetensors"))
    (broken / "manifest.json").write_text("[]")
    with pytest.raises(CheckpointError, match="not a bundle manifest"):
        M4WorldEnv("merge_cut_in", backend="world_model", checkpoint=str(broken))


def test_scenario_adapters_are_applied_to_the_student(active_bundle, tmp_path):
    import shutil

    import torch

    from m4world_env.scenario import load_scenario
    from world_model.lora import LoraConfig, add_adapter, base_fingerprint, loaded_adapters, save_adapter
    from world_model.rollout.runtime import load_world_model

    bundle = shutil.copytree(active_bundle, tmp_path / "bundle")  # the adapter is written into it
    wm = load_world_model(bundle)
    base = base_fingerprint(wm.student)
    lora = LoraConfig(rank=2)
    add_adapter(wm.student, "rare_case", lora)
    with torch.no_grad():
        for name, p in wm.student.named_parameters():
            if "lora_B" in name:
                p.normal_()  # a non-trivial adapter
    save_adapter(wm.student, "rare_case", bundle / "adapters" / "rare_case", lora, base)
    scenario = load_scenario("merge_cut_in").model_copy(update={"adapters": ["rare_case"]})
    env = M4WorldEnv(scenario, backend="world_model", checkpoint=str(bundle), config=KEYS)
    assert loaded_adapters(env.backend.wm.student) == ["rare_case"]
    plain = M4WorldEnv("merge_cut_in", backend="world_model", checkpoint=str(bundle), config=KEYS)
    a, _ = env.reset(seed=0)
    b, _ = plain.reset(seed=0)
    a = env.step(np.zeros(2, np.float32))[0]
    b = plain.step(np.zeros(2, np.float32))[0]
    assert not np.array_equal(a["cameras"], b["cameras"])
    bad = load_scenario("merge_cut_in").model_copy(update={"adapters": ["no_such_adapter"]})
    with pytest.raises((FileNotFoundError, ValueError, KeyError), match="no_such_adapter"):
        M4WorldEnv(bad, backend="world_model", checkpoint=str(bundle), config=KEYS)


def test_a_reference_model_adapter_goes_to_the_reference_model(tiny_bundle, tmp_path):
    """A scenario's adapter trained on the bundle's reference model changes reset()'s first frame
    and leaves the student alone; one trained on neither model is refused, naming both."""
    from m4world_env.scenario import load_scenario
    from world_model.bundle import load_bundle_files, save_bundle
    from world_model.lora import (
        AdapterMismatchError,
        LoraConfig,
        add_adapter,
        base_fingerprint,
        loaded_adapters,
        remove_adapters,
        save_adapter,
    )
    from world_model.rollout.runtime import load_world_model

    files = load_bundle_files(tiny_bundle)
    gen = torch.Generator().manual_seed(0)
    tensors = dict(files.tensors)
    for part in ("student", "reference"):  # adaLN-Zero: an untrained DiT's output ignores its blocks
        tensors[part] = {k: v + 0.05 * torch.randn(v.shape, generator=gen) for k, v in tensors[part].items()}
    configs = {"reference": files.component_config("reference")}
    bundle = save_bundle(tmp_path / "bundle", files.model_config, tensors, component_configs=configs)
    wm = load_world_model(bundle)
    lora = LoraConfig(rank=2)

    def save(model, name, fingerprint):
        add_adapter(model, name, lora)
        with torch.no_grad():
            for pname, param in model.named_parameters():
                if "lora_B" in pname:
                    param.normal_()
        save_adapter(model, name, tmp_path / "adapters" / name, lora, fingerprint)
        remove_adapters(model)
        return str(tmp_path / "adapters" / name)

    ref_case = save(wm.reference, "ref_case", base_fingerprint(wm.reference))
    foreign = save(wm.student, "foreign", "0" * 64)  # trained on some other base
    scenario = load_scenario("merge_cut_in").model_copy(update={"adapters": [ref_case]})
    env = M4WorldEnv(scenario, backend="world_model", checkpoint=str(bundle), config=KEYS)
    assert loaded_adapters(env.backend.wm.reference) == ["ref_case"] and loaded_adapters(env.backend.wm.student) == []
    plain = M4WorldEnv("merge_cut_in", backend="world_model", checkpoint=str(bundle), config=KEYS)
    assert not np.array_equal(env.reset(seed=0)[0]["cameras"], plain.reset(seed=0)[0]["cameras"])
    bad = load_scenario("merge_cut_in").model_copy(update={"adapters": [foreign]})
    with pytest.raises(AdapterMismatchError, match="student.*reference model"):
        M4WorldEnv(bad, backend="world_model", checkpoint=str(bundle), config=KEYS)
    # A refused list loads nothing; loading the same adapter twice is a no-op, another under its name is refused.
    wm = load_world_model(bundle)
    with pytest.raises(AdapterMismatchError):
        wm.apply_adapters([ref_case, foreign])
    assert loaded_adapters(wm.reference) == []
    assert wm.apply_adapters([ref_case]) == wm.apply_adapters([ref_case]) == ["ref_case"]
    import shutil

    twin = shutil.copytree(ref_case, tmp_path / "twin" / "ref_case")
    with pytest.raises(ValueError, match="already has an adapter named 'ref_case'"):
        wm.apply_adapters([twin])


def test_model_dtype_option_sets_the_dit_precision(tiny_bundle):
    for dtype, want in (("bfloat16", torch.bfloat16), ("float32", torch.float32)):
        env = M4WorldEnv(
            "merge_cut_in", backend="world_model", checkpoint=str(tiny_bundle), config={"model": {"dtype": dtype}}
        )
        obs, _ = env.reset(seed=0)
        student = env.backend.wm.student
        assert next(student.parameters()).dtype == want
        assert student.cfg.dit.autocast_bf16 == (dtype == "bfloat16")
        obs, *_ = env.step(env.action_space.sample())
        assert np.isfinite(obs["lidar"]).all()
        env.close()


def test_refresh_steps_option_reaches_the_student_and_is_checked(tiny_bundle):
    def episode(model: dict, want: tuple[int, ...]) -> list[np.ndarray]:
        env = M4WorldEnv("merge_cut_in", backend="world_model", checkpoint=str(tiny_bundle), config={"model": model})
        perturbed(env.backend.wm.student)  # the untrained student's zero output ignores its context
        obs, _ = env.reset(seed=0)
        frames = [obs["lidar"]] + [env.step(np.zeros(2, np.float32))[0]["lidar"] for _ in range(3)]
        assert env.backend.wm.student_cfg.streaming.resolved_refresh_steps() == want
        env.close()
        return frames

    # The bundle's default refreshes at the last two of the 4 denoising steps; 'all' at every step.
    default, every = episode({}, (2, 3)), episode({"refresh_steps": "all"}, (0, 1, 2, 3))
    np.testing.assert_array_equal(default, episode({"refresh_steps": [-2, -1]}, (2, 3)))
    first = episode({"refresh_steps": [0]}, (0,))
    np.testing.assert_array_equal(every[0], first[0])  # the reset frame does not involve the student
    for other in (every, first):
        assert any(not np.array_equal(a, b) for a, b in zip(default[1:], other[1:], strict=True))
    # Negative indices count from the last of denoising_steps: here the last two of 2 are both.
    episode({"refresh_steps": [-2, -1], "denoising_steps": 2}, (0, 1))
    episode({"denoising_steps": 1}, (0,))  # of the bundle's last two, only the last names a step of one
    episode({"context_refresh": False}, ())  # the default is ignored without refresh
    beyond = {"model": {"refresh_steps": [4]}}  # the student takes 4 steps: 0 to 3
    with pytest.raises(InvalidOptionError, match="refresh_steps"):
        M4WorldEnv("merge_cut_in", backend="world_model", checkpoint=str(tiny_bundle), config=beyond)


def test_sink_frames_option_keeps_the_first_frame_in_context(tiny_bundle):
    def episode(model: dict) -> tuple[list[np.ndarray], list[int], int]:
        """LiDAR of the reset and of 4 steps, the index of the frame each shows, the student's window."""
        env = M4WorldEnv("merge_cut_in", backend="world_model", checkpoint=str(tiny_bundle), config={"model": model})
        sink_frames = model.get("sink_frames", StreamingConfig().sink_frames)
        assert env.backend.wm.student_cfg.streaming.sink_frames == sink_frames
        perturbed(env.backend.wm.student)
        engine = env.backend.rollouts.engine
        frames, index = [env.reset(seed=0)[0]["lidar"]], [0]
        for _ in range(4):
            frames.append(env.step(np.zeros(2, np.float32))[0]["lidar"])
            index.append(engine.position - 1)
        env.close()
        return frames, index, env.backend.wm.cfg.clip.context_frames

    (plain, index, window), (sink, *_) = episode({"sink_frames": 0}), episode({"sink_frames": 1})
    np.testing.assert_array_equal(sink, episode({})[0])  # one sink frame is the default
    # While the first frame is still in the rolling window the sink adds nothing; once it has left
    # (frames after the window's first `window`), the sink keeps it in context and they change.
    assert index[0] < window < index[-1]
    for f, a, b in zip(index, plain, sink, strict=True):
        assert np.array_equal(a, b) == (f <= window), f


def _bundle_with_completion_adapter(bundle, root):
    """A completion adapter (random LoRA B) for category "van" (merge_cut_in's cutting van) on
    ``bundle``'s reference model (``active_bundle``: its output depends on its blocks), saved
    under ``root``. Returns the bundle and the adapter's path."""
    from world_model.lora import LoraConfig, add_adapter, base_fingerprint, remove_adapters, save_adapter
    from world_model.rollout.runtime import load_world_model

    wm = load_world_model(bundle)
    lora = LoraConfig(rank=2)
    add_adapter(wm.reference, "van_completion", lora)
    with torch.no_grad():
        for name, param in wm.reference.named_parameters():
            if "lora_B" in name:
                param.normal_()
    path = root / "adapters" / "van_completion"
    train = {"case": "van", "reference_tasks": True}
    save_adapter(wm.reference, "van_completion", path, lora, base_fingerprint(wm.reference), {"train": train})
    remove_adapters(wm.reference)
    return bundle, path


def test_a_completion_adapter_draws_its_category_into_the_first_frame_only(active_bundle, tmp_path):
    """A reference-model adapter trained in the completion task acts at reset() only inside its
    category's projected boxes: the controls pass runs without it (every latent cell outside the
    boxes equals the plain model's), a frame without the category and a first frame anchored on
    the user's images are untouched, and the adapters active before are active again after."""
    from m4world_env.scenario import load_scenario
    from world_model.lora import LoraConfig, add_adapter, base_fingerprint, read_adapter, remove_adapters, save_adapter
    from world_model.model.reference import category_region
    from world_model.rollout.runtime import load_world_model

    bundle, path = _bundle_with_completion_adapter(active_bundle, tmp_path)
    assert read_adapter(path)[0].completes == "van"

    def first(scenario, adapters, **reset):
        scenario = load_scenario(scenario).model_copy(update={"adapters": adapters})
        env = M4WorldEnv(scenario, backend="world_model", checkpoint=str(bundle), config=KEYS)
        obs, _ = env.reset(seed=0, **reset)
        return env, obs, env.backend.rollouts.engine.last[0, 0]  # the first frame's latents

    env, adapted, lat = first("merge_cut_in", [str(path)])
    _, plain, plain_lat = first("merge_cut_in", [])
    region = category_region([env._frame], "van", env.backend.wm.cfg, env.backend.wm.first_frames.cfg)
    region = torch.from_numpy(region[0])
    assert region[:-1].any()  # the van is in a camera
    outside = ~region[:, None].expand_as(lat)
    assert torch.equal(lat[outside], plain_lat[outside]) and not torch.equal(lat, plain_lat)
    assert not np.array_equal(adapted["cameras"], plain["cameras"])
    assert env.backend.wm.reference.blocks[0].attn.q.active_adapters == ["van_completion"]  # restored
    _, empty, _ = first("empty_highway", [str(path)])
    _, empty_plain, _ = first("empty_highway", [])
    assert np.array_equal(empty["cameras"], empty_plain["cameras"])
    image = {"FRONT": plain["cameras"][0]}
    _, anchored, _ = first("merge_cut_in", [str(path)], options={"reference": image})
    _, anchored_plain, _ = first("merge_cut_in", [], options={"reference": image})
    assert np.array_equal(anchored["cameras"], anchored_plain["cameras"])
    remove_adapters(env.backend.wm.reference)  # removed by hand: reset() no longer completes
    assert np.array_equal(env.reset(seed=0)[0]["cameras"], plain["cameras"])
    odd = tmp_path / "adapters" / "odd"
    train = {"case": "spaceship", "reference_tasks": True}
    wm, lora = load_world_model(bundle), LoraConfig(rank=2)
    add_adapter(wm.reference, "odd", lora)
    save_adapter(wm.reference, "odd", odd, lora, base_fingerprint(wm.reference), {"train": train})
    remove_adapters(wm.reference)
    with pytest.raises(ValueError, match="'spaceship' is not one of"):
        load_world_model(bundle).apply_adapters([str(odd)])


def test_vector_env_with_a_completion_adapter_equals_single_envs(active_bundle, tmp_path):
    """A scenario's completion adapter in the batched vector env: each row's reset completes the
    van as its single env does (seeds s + i), and the rollouts stay equal."""
    import yaml

    from m4world_env.scenario import SCENARIOS_DIR

    bundle, adapter = _bundle_with_completion_adapter(active_bundle, tmp_path)
    scenario = tmp_path / "van.yaml"
    scenario.write_text(
        yaml.safe_dump(
            {**yaml.safe_load((SCENARIOS_DIR / "merge_cut_in.yaml").read_text()), "adapters": [str(adapter)]}
        )
    )
    n, seed, cfg = 2, 3, {"observation_keys": ["cameras", "lidar"]}
    kw = {"scenario": str(scenario), "backend": "world_model", "checkpoint": str(bundle), "config": cfg}
    venv = gym.make_vec("M4World-v0", num_envs=n, vectorization_mode="vector_entry_point", **kw)
    singles = [M4WorldEnv(kw["scenario"], backend="world_model", checkpoint=str(bundle), config=cfg) for _ in range(n)]
    plain = M4WorldEnv("merge_cut_in", backend="world_model", checkpoint=str(bundle), config=cfg)
    vobs, _ = venv.reset(seed=seed)
    sobs = [env.reset(seed=seed + i)[0] for i, env in enumerate(singles)]
    assert not np.array_equal(sobs[0]["cameras"], plain.reset(seed=seed)[0]["cameras"])  # completed
    actions = np.zeros((n, 2), np.float32)
    for step in range(2):
        if step:
            vobs = venv.step(actions)[0]
            sobs = [env.step(a)[0] for env, a in zip(singles, actions, strict=True)]
        assert_rows_equal_singles(vobs, sobs, step)


def test_an_image_given_to_an_inserted_object_reaches_the_model(active_bundle, tmp_path):
    import cv2

    from m4world_env.scenario import ScenarioError

    image = tmp_path / "truck.png"
    cv2.imwrite(str(image), np.tile(np.array([0, 0, 255], np.uint8), (24, 24, 1)))
    spec = {"id": "new", "category": "truck", "track": {"kind": "static", "x": 20.0, "y": 0.0}}

    def after_insert(**extra) -> np.ndarray:
        env = M4WorldEnv("merge_cut_in", backend="world_model", checkpoint=str(active_bundle), config=KEYS)
        env.reset(seed=0)
        env.insert_object({**spec, **extra})
        return env.step(np.zeros(2, np.float32))[0]["cameras"]

    assert not np.array_equal(after_insert(image=str(image)), after_insert())
    env = M4WorldEnv("merge_cut_in", backend="world_model", checkpoint=str(active_bundle), config=KEYS)
    env.reset(seed=0)
    with pytest.raises(ScenarioError, match="image"):
        env.insert_object({**spec, "image": str(tmp_path / "missing.png")})
    with pytest.raises(ScenarioError, match="image"):
        env.edit_object("cutting_van", image=str(tmp_path / "missing.png"))
    env.step(np.zeros(2, np.float32))  # still usable


def test_env_streams_exactly_as_the_report_headline_row(tiny_bundle):
    """The report's student row runs load_world_model's settings: the env must run the same."""
    env = M4WorldEnv("merge_cut_in", backend="world_model", checkpoint=str(tiny_bundle))
    report_wm = load_world_model(str(tiny_bundle))
    assert env.backend.wm.student_cfg == report_wm.student_cfg
    assert env.backend.streaming == report_wm.streaming == report_wm.student_cfg.streaming == StreamingConfig()
    env.close()
