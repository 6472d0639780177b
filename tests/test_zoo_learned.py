"""The zoo's learned family: its features, its training command, its weights and its policies."""

import gymnasium as gym
import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file

import m4world_env  # noqa: F401
from m4world_env.policies import RandomPolicy
from m4world_env.zoo import learned
from m4world_env.zoo import train_learned as tl
from m4world_env.zoo.base import SensorGeometry
from m4world_env.zoo.learned import (
    LEARNED_SPECS,
    LearnedPolicy,
    LearnedSpec,
    extract_features,
    learned_member,
    learned_members,
)

SCENARIO = "highway_sunny_day"
TINY_RECIPE = tl.RecordingRecipe(episode_steps=15, scenarios=(SCENARIO,))
TINY_SPEC = LearnedSpec("bc_test_both", "both", episodes=2, train_steps=150, seed=7)


@pytest.fixture(scope="module")
def env():
    e = gym.make(
        "M4World-v0", scenario=SCENARIO, backend="procedural", config={"observation_keys": ["cameras", "lidar"]}
    )
    yield e
    e.close()


@pytest.fixture(scope="module")
def geometry(env):
    return SensorGeometry.of_env(env)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """TINY_SPEC trained on two 15-step episodes: (weights folder, demonstrations folder, result)."""
    root = tmp_path_factory.mktemp("zoo_learned")
    (result,) = tl.train([TINY_SPEC], root / "weights", root / "work", TINY_RECIPE, log=False)
    return root / "weights", root / "work", result


def _observation(geometry):
    """A hand-made observation: each view a flat colour of its own, no LiDAR return anywhere."""
    views, (h, w) = geometry.rig.num_views, geometry.rig.resolution
    cameras = np.zeros((views, h, w, 3), dtype=np.uint8)
    for v in range(views):
        cameras[v] = (10 * v, 20, 30)
    lidar = np.zeros((geometry.lidar.beams, geometry.lidar.azimuth), dtype=np.float32)
    return {"cameras": cameras, "lidar": lidar}


# -- features --


def test_features_have_the_network_shapes_and_read_the_front_camera(geometry):
    f = extract_features(_observation(geometry), 15.0, geometry)
    assert f.camera.shape == (3, *learned.CAMERA_SHAPE) and f.camera.dtype == np.float32
    assert f.lidar.shape == (1, learned.LIDAR_BEAMS, learned.LIDAR_COLUMNS) and f.lidar.dtype == np.float32
    assert f.speed.shape == (1,) and f.speed[0] == pytest.approx(15.0 / learned.SPEED_SCALE)
    front = geometry.view_index("FRONT")
    np.testing.assert_allclose(f.camera[:, 0, 0], np.array([10 * front, 20, 30]) / 255.0, rtol=1e-6)
    assert f.camera.min() >= 0.0 and f.camera.max() <= 1.0


def test_a_ray_without_return_reads_as_far_as_the_sensor_sees(geometry):
    f = extract_features(_observation(geometry), 0.0, geometry)
    np.testing.assert_array_equal(f.lidar, 1.0)


def test_the_lidar_crop_is_the_forward_half_min_pooled(geometry):
    obs = _observation(geometry)
    ranges = obs["lidar"]
    assert learned.lidar_columns(geometry) == (256, 768)
    ranges[:, 255] = ranges[:, 768] = 5.0  # just outside the crop: must not show
    ranges[:, 256] = 10.0  # the first column of the crop (+90 deg, left)
    ranges[:, 512] = 20.0  # straight ahead
    ranges[:, 513:516] = (50.0, 40.0, 60.0)  # the same bin: the nearest return is kept
    ranges[:, 767] = 30.0  # the last column (-90 deg, right)
    ranges[3, 400] = 150.0  # beyond max range: clipped to it
    lidar = extract_features(obs, 0.0, geometry).lidar[0]
    bin_of = {256: 0, 512: (512 - 256) // 4, 767: learned.LIDAR_COLUMNS - 1}
    expected = np.ones_like(lidar)
    expected[:, bin_of[256]] = 0.1
    expected[:, bin_of[512]] = 0.2
    expected[:, bin_of[767]] = 0.3
    np.testing.assert_allclose(lidar, expected, rtol=1e-6)
    assert bin_of[512] == 64  # straight ahead is the middle of the crop


def test_features_refuse_a_lidar_of_another_layout(geometry):
    obs = _observation(geometry)
    obs["lidar"] = obs["lidar"][:16]
    with pytest.raises(ValueError, match="32-beam LiDAR"):
        extract_features(obs, 0.0, geometry)


# -- the network and the members --


@pytest.mark.parametrize("sensors", learned.SENSOR_SETS)
def test_the_network_maps_features_to_an_action_in_range(sensors, geometry):
    net = learned.BehaviourCloningNet(sensors).eval()
    f = extract_features(_observation(geometry), 20.0, geometry)
    with torch.no_grad():
        out = net(*learned.features_to_tensors(f))
    assert out.shape == (1, 2) and bool((out.abs() <= 1.0).all())


def test_the_learned_members_are_listed_without_their_weights():
    members = learned_members()
    assert len(members) >= 6
    assert len({m.name for m in members}) == len(members) and len({m.seed for m in members}) == len(members)
    for member, spec in zip(members, LEARNED_SPECS, strict=True):
        assert member.family == "learned" and member.version == 1 and member.name == spec.name
        assert f"{spec.episodes} recorded episodes" in member.description
        assert {"cameras": "camera", "lidar": "LiDAR", "both": "camera and forward LiDAR"}[spec.sensors] in (
            member.description
        )
    assert {s.sensors for s in LEARNED_SPECS} == set(learned.SENSOR_SETS)


def test_a_missing_weight_file_is_named_when_the_member_is_built(tmp_path, geometry):
    member = learned_member(TINY_SPEC, tmp_path)  # listing it needs no file
    with pytest.raises(FileNotFoundError, match=r"bc_test_both\.safetensors.*make zoo"):
        member.build(geometry, seed=0)


@pytest.mark.parametrize("spec", LEARNED_SPECS, ids=lambda s: s.name)
def test_the_shipped_weights_match_their_member(spec, geometry, env):
    path = learned.weights_path(spec)
    if not path.is_file():
        pytest.skip(f"{path.name} not trained (make zoo)")
    policy = learned_member(spec).build(geometry, seed=0)
    meta = policy.metadata
    assert (meta["name"], meta["sensors"], meta["version"], meta["seed"]) == (
        spec.name,
        spec.sensors,
        str(spec.version),
        str(spec.seed),
    )
    assert (meta["episodes"], meta["train_steps"]) == (str(spec.episodes), str(spec.train_steps))
    assert path.stat().st_size <= 400_000
    obs, info = env.reset(seed=0)
    action = policy(obs, info)
    assert action.shape == (2,) and action.dtype == np.float32 and bool(np.all(np.abs(action) <= 1.0))


def test_all_shipped_weights_fit_the_size_budget():
    total = sum(p.stat().st_size for p in learned.WEIGHTS_DIR.glob("*"))
    assert total <= 10_000_000
    assert all(p.suffix == ".safetensors" for p in learned.WEIGHTS_DIR.glob("*"))


# -- training --


def test_training_writes_loadable_weights_with_their_metadata(trained, geometry, env):
    weights, _, result = trained
    assert sorted(p.name for p in weights.iterdir()) == ["bc_test_both.safetensors"]  # no temporary file left
    with safe_open(str(result.path), framework="pt") as f:
        meta = f.metadata()
    assert meta["format"] == learned.WEIGHTS_FORMAT
    assert (meta["name"], meta["version"], meta["seed"], meta["sensors"]) == ("bc_test_both", "1", "7", "both")
    assert (meta["episodes"], meta["train_steps"]) == ("2", "150")
    assert int(meta["samples"]) == result.samples and 2 <= result.samples <= 2 * TINY_RECIPE.episode_steps
    assert float(meta["final_loss"]) == pytest.approx(result.final_loss, rel=1e-4)
    policy = learned_member(TINY_SPEC, weights).build(geometry, seed=0)
    obs, info = env.reset(seed=3)
    first = policy(obs, info)
    assert first.shape == (2,) and first.dtype == np.float32
    threads = torch.get_num_threads()
    np.testing.assert_array_equal(LearnedPolicy(geometry, result.path)(obs, info), first)  # deterministic
    assert torch.get_num_threads() == threads  # the one-thread forward pass restores the setting


def test_demonstrations_are_cached_and_training_is_deterministic(trained, tmp_path, monkeypatch):
    weights, work, _ = trained
    cached = tl.load_or_record(work, TINY_RECIPE, 1, log=False)[0]
    again = tl.record_episode(0, TINY_RECIPE)
    assert cached.keys() == again.keys()
    for k in cached:
        np.testing.assert_array_equal(cached[k], again[k], err_msg=k)

    def record_again(*_args, **_kwargs):
        raise AssertionError("the cached episodes should have been read, not recorded again")

    monkeypatch.setattr(tl, "record_episode", record_again)
    episodes = tl.load_or_record(work, TINY_RECIPE, TINY_SPEC.episodes, log=False)
    assert len(episodes) == 2 and all(len(e["action"]) == len(e["camera"]) for e in episodes)
    (retrained,) = tl.train([TINY_SPEC], tmp_path, work, TINY_RECIPE, log=False)
    assert (weights / "bc_test_both.safetensors").read_bytes() == retrained.path.read_bytes()
    first, second = load_file(str(weights / "bc_test_both.safetensors")), load_file(str(retrained.path))
    assert first.keys() == second.keys()
    for k in first:
        torch.testing.assert_close(first[k], second[k], rtol=0, atol=0)


def test_the_recording_plan_covers_scenarios_and_styles_from_seed_10000():
    recipe = tl.RecordingRecipe()
    plans = [recipe.plan(i) for i in range(3 * len(recipe.scenarios))]
    assert {p[0] for p in plans} == set(recipe.scenarios)
    assert {(p[0], p[1]) for p in plans} == {(s, st) for s in recipe.scenarios for st in tl.STYLES}
    assert min(p[2] for p in plans) == tl.FIRST_SEED >= 1000
    assert recipe.key() != tl.RecordingRecipe(episode_steps=10).key()


def _mean_pdms(env, act, seeds=(0, 1), steps=30):
    scores = []
    for seed in seeds:
        obs, info = env.reset(seed=seed)
        for _ in range(steps):
            obs, _, terminated, truncated, info = env.step(act(obs, info))
            if terminated or truncated:
                break
        scores.append(info["episode_metrics"]["pdms"])
    return float(np.mean(scores))


def test_a_member_trained_on_two_clips_beats_random_actions(trained, env, geometry):
    weights, _, _ = trained
    member = learned_member(TINY_SPEC, weights)
    policies = {}

    def learned_act(obs, info):
        return policies["current"](obs, info)

    scores = []
    for seed in (0, 1):
        policies["current"] = member.build(geometry, seed=seed)
        scores.append(_mean_pdms(env, learned_act, seeds=(seed,)))
    random = RandomPolicy(seed=0)
    random_score = _mean_pdms(env, lambda obs, info: random(env.unwrapped))
    assert np.mean(scores) > random_score + 0.2, (scores, random_score)


# -- the command line --


@pytest.mark.parametrize(
    ("argv", "named"),
    [
        (["--out", "{file}"], "--out"),
        (["--out", "{dir}", "--workdir", "{file}"], "--workdir"),
        (["--out", "{dir}", "--members", "bc_both_large", "nope"], "--members nope"),
    ],
)
def test_the_command_refuses_bad_arguments_before_any_work(argv, named, tmp_path, capsys, monkeypatch):
    afile = tmp_path / "a_file"
    afile.write_text("")
    monkeypatch.setattr(tl, "train", lambda *a, **k: pytest.fail("no work may start on bad arguments"))
    with pytest.raises(SystemExit) as exc:
        tl.main([a.format(file=afile, dir=tmp_path / "out") for a in argv])
    assert exc.value.code == 2
    assert named in capsys.readouterr().err
