"""Property-based fuzzing through the public interface: every input either raises one of the
project's exceptions, with a message that names what was wrong, or gives an env whose observations
and rewards are finite and inside its spaces. Never an internal crash, a hang or a NaN.

Derandomized (hypothesis' database off, a fixed example stream), so CI sees the same cases
every run; ``FUZZ_EXAMPLES`` scales the number of cases per property.
"""

import copy
import json
import math
import numbers
import shutil
import zlib
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

import m4world_env  # noqa: F401 (registers M4World-v0)
from m4world_env import scenario as bounds
from m4world_env.config import OBSERVATION_KEYS, EnvConfig, InvalidOptionError, UnknownOptionError
from m4world_env.env import RENDER_MODES
from m4world_env.scenario import SCENARIOS_DIR, ScenarioError, scenario_from_dict
from m4world_env.traffic import ActionError
from m4world_env.traffic.population import EDITABLE, UnknownObjectError
from tests.fuzz_settings import EXAMPLES, FUZZ
from world_model.bundle import CheckpointError, load_bundle_files

SMALL = {"height": 16, "width": 32}
# What a user may be told: the project's own exceptions (and TypeError for a wrong Python type
# in the reset options, as the standard library would).
REFUSALS = (ScenarioError, InvalidOptionError, UnknownOptionError, ActionError, UnknownObjectError, CheckpointError)

# Values a careless user writes: wrong types, non-finite and absurd numbers, empty things.
NASTY = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(10**12), max_value=10**12),
    st.sampled_from([10**400, -(10**400)]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([1e-300, 1e300, -1e300, 0.0, -0.0, 1e7, 2.5]),
    st.text(max_size=8),
    st.lists(st.integers(-5, 5), max_size=4),
    st.dictionaries(st.text(max_size=4), st.integers(0, 3), max_size=2),
)


def _assert_finite_inside(env, obs, reward=0.0):
    space = env.observation_space
    for key, value in obs.items():
        assert np.all(np.isfinite(value)), key
        assert space[key].contains(value), key
    assert np.isfinite(reward)


def _paths(tree, prefix=()):
    """Every (path, value) leaf and subtree of a nested dict/list."""
    if isinstance(tree, dict):
        for k, v in tree.items():
            yield (*prefix, k), v
            yield from _paths(v, (*prefix, k))
    elif isinstance(tree, list):
        for i, v in enumerate(tree):
            yield (*prefix, i), v
            yield from _paths(v, (*prefix, i))


BASES = {p.stem: yaml.safe_load(p.read_text()) for p in sorted(SCENARIOS_DIR.glob("*.yaml"))}


# What a YAML file can hold besides: bytes (``!!binary``) where text belongs.
NASTY_YAML = st.one_of(NASTY, st.binary(max_size=4))


@st.composite
def mutated_scenarios(draw):
    data = copy.deepcopy(BASES[draw(st.sampled_from(sorted(BASES)))])
    for _ in range(draw(st.integers(1, 3))):
        paths = [p for p, _ in _paths(data)]
        path = draw(st.sampled_from(paths))
        cur = data
        for k in path[:-1]:
            cur = cur[k]
        if draw(st.booleans()):
            cur[path[-1]] = draw(NASTY_YAML)
        elif isinstance(cur, dict):
            del cur[path[-1]]
    return data


def _assert_within_documented_bounds(data, scenario) -> None:
    """An accepted scenario holds no bytes and respects docs/scenarios.md's physical bounds."""
    assert not any(isinstance(v, bytes) for _, v in _paths(data))
    road, traffic = scenario.road, scenario.traffic
    assert scenario.duration * scenario.policy_frequency >= 1 - bounds.TIME_TOLERANCE
    limits = [road.speed_limit, getattr(road, "ramp_speed_limit", road.speed_limit)]
    assert all(bounds.MIN_SPEED_LIMIT_MPS <= v <= bounds.MAX_SPEED_MPS for v in limits)
    assert bounds.MIN_TRAFFIC_DENSITY <= traffic.density <= bounds.MAX_TRAFFIC_DENSITY
    assert 0 < sum(traffic.mix.values()) < math.inf
    assert scenario.ego.longitudinal <= road.length_along(scenario.ego.lane)
    for obj in scenario.objects:
        assert all(bounds.MIN_OBJECT_SIZE_M <= v <= bounds.MAX_OBJECT_SIZE_M for v in obj.box_size)
        assert getattr(obj.track, "duration", bounds.MIN_LANE_CHANGE_S) >= bounds.MIN_LANE_CHANGE_S


@FUZZ
@given(mutated_scenarios())
def test_mutated_scenarios_are_refused_by_field_or_run_finite(data):
    try:
        scenario = scenario_from_dict(data, "fuzz.yaml")
    except ScenarioError as e:
        assert "fuzz.yaml" in str(e)
        return
    _assert_within_documented_bounds(data, scenario)
    env = gym.make("M4World-v0", scenario=scenario, config={**SMALL, "observation_keys": ["cameras", "lidar", "state"]})
    try:
        obs, _ = env.reset(seed=0)
        _assert_finite_inside(env, obs)
        for _ in range(2):
            obs, reward, terminated, truncated, _ = env.step(env.action_space.sample())
            _assert_finite_inside(env, obs, reward)
            if terminated or truncated:
                break
    finally:
        env.close()


CONFIG_KEYS = [
    "action_type",
    "observation_keys",
    "height",
    "width",
    "state_objects",
    "offroad_terminal",
    "reward",
    "model",
    "bogus",
    7,
]
REWARD_KEYS = ["collision", "high_speed", "right_lane", "on_road", "progress", "speed_range", "normalize"]
MODEL_KEYS = ["denoising_steps", "context_refresh", "refresh_steps", "sink_frames", "device", "dtype", "compile"]


@st.composite
def configs(draw):
    config = {}
    for key in draw(st.lists(st.sampled_from(CONFIG_KEYS), max_size=3, unique=True)):
        if key == "reward":
            config[key] = {
                k: draw(NASTY) for k in draw(st.lists(st.sampled_from(REWARD_KEYS), max_size=2, unique=True))
            }
        elif key == "model":
            config[key] = {k: draw(NASTY) for k in draw(st.lists(st.sampled_from(MODEL_KEYS), max_size=2, unique=True))}
        else:
            config[key] = draw(NASTY)
    return draw(st.one_of(st.just(config), NASTY))


@FUZZ
@given(configs())
def test_config_dicts_are_refused_by_name_or_run_finite(config):
    try:
        env = gym.make("M4World-v0", scenario="highway_sunny_day", config=config)
    except (InvalidOptionError, UnknownOptionError) as e:
        assert "config" in str(e)
        return
    try:
        obs, _ = env.reset(seed=0)
        _assert_finite_inside(env, obs)
        obs, reward, *_ = env.step(env.action_space.sample())
        _assert_finite_inside(env, obs, reward)
    finally:
        env.close()


@settings(FUZZ, max_examples=max(EXAMPLES // 4, 10))
@given(
    keys=st.one_of(NASTY, st.lists(st.sampled_from([*OBSERVATION_KEYS, "x"]), max_size=5), st.sets(st.text(max_size=6)))
)
def test_observation_keys_are_refused_by_name_or_observed_once_each(keys):
    try:
        cfg = EnvConfig.from_dict({"observation_keys": keys})
    except InvalidOptionError as e:
        assert "config.observation_keys" in str(e)
        return
    assert isinstance(keys, list | tuple | set) and not isinstance(keys, str)
    assert sorted(cfg.observation_keys) == sorted(set(keys)) and len(cfg.observation_keys) == len(keys)


@settings(FUZZ, max_examples=max(EXAMPLES // 4, 10))
@given(mode=st.one_of(NASTY, st.sampled_from([*RENDER_MODES, b"rgb_array", ("rgb_array",)])))
def test_render_modes_are_refused_by_name_or_rendered(mode):
    try:
        env = gym.make("M4World-v0", scenario="highway_sunny_day", render_mode=mode, config=SMALL)
    except InvalidOptionError as e:
        assert "render_mode" in str(e)
        return
    try:
        assert mode is None or mode in (*RENDER_MODES, "human")  # gymnasium draws "human" from rgb_array
        if mode in RENDER_MODES:
            env.reset(seed=0)
            assert env.render() is not None
    finally:
        env.close()


def _is_seed(seed) -> bool:
    return seed is None or (isinstance(seed, numbers.Integral) and not isinstance(seed, bool) and seed >= 0)


SEEDS = st.one_of(
    NASTY,
    st.integers(0, 2**70),
    st.sampled_from([np.int64(3), np.uint8(2), np.float64(3.0), np.bool_(True), np.array([1, 2]), np.array(2)]),
    st.lists(st.one_of(st.none(), st.integers(-2, 9), st.booleans(), st.floats()), min_size=1, max_size=3),
)


@settings(FUZZ, max_examples=max(EXAMPLES // 4, 10))
@given(seed=SEEDS)
def test_seeds_are_refused_by_name_or_seed_the_single_and_the_vector_env(vector_env, procedural_envs, seed):
    env = procedural_envs["continuous"]
    try:
        env.reset(seed=seed)
        assert _is_seed(seed)
    except InvalidOptionError as e:
        assert "reset(seed=" in str(e) and not _is_seed(seed)
    try:
        vector_env.reset(seed=seed)
        per_env = seed.tolist() if isinstance(seed, np.ndarray) else seed
        assert _is_seed(seed) or (isinstance(per_env, list) and len(per_env) == 2 and all(map(_is_seed, per_env)))
    except InvalidOptionError as e:
        assert "reset(seed=" in str(e)


ACTIONS = st.one_of(
    NASTY,
    st.lists(NASTY, min_size=0, max_size=3),
    st.lists(st.floats(-2, 2), min_size=2, max_size=2),
    st.sampled_from(
        [np.array([0.5 + 1j, 0]), np.array(["a", "b"]), np.array([True, False]), np.zeros((2, 1)), np.zeros(2, "M8[s]")]
    ),
    # What a torch policy hands over: tensors that need grad, in bfloat16, complex, of ints or bools.
    st.builds(
        lambda values, dtype, grad: torch.tensor(values, dtype=dtype, requires_grad=grad and dtype.is_floating_point),
        st.lists(st.floats(-2, 2), min_size=0, max_size=3),
        st.sampled_from([torch.float32, torch.bfloat16, torch.float64, torch.complex64, torch.int64, torch.bool]),
        st.booleans(),
    ),
)


@pytest.fixture(scope="module")
def vector_env():
    venv = gym.make_vec("M4World-v0", num_envs=2, vectorization_mode="vector_entry_point", config=SMALL)
    yield venv
    venv.close()


@pytest.fixture(scope="module")
def procedural_envs():
    envs = {
        t: gym.make("M4World-v0", scenario="highway_sunny_day", config={**SMALL, "action_type": t})
        for t in ("continuous", "discrete_meta")
    }
    yield envs
    for env in envs.values():
        env.close()


@FUZZ
@given(kind=st.sampled_from(["continuous", "discrete_meta"]), action=ACTIONS)
def test_actions_are_refused_or_stepped_finite(procedural_envs, kind, action):
    env = procedural_envs[kind]
    env.reset(seed=0)
    try:
        obs, reward, *_ = env.step(action)
    except ActionError as e:
        assert "action" in str(e)
        return
    _assert_finite_inside(env, obs, reward)


@settings(FUZZ, max_examples=max(EXAMPLES // 20, 5))
@given(
    values=st.lists(st.floats(-1, 1, width=16), min_size=2, max_size=2),
    dtype=st.sampled_from([torch.float32, torch.float64, torch.bfloat16, torch.float16]),
    grad=st.booleans(),
)
def test_a_tensor_action_steps_as_its_values(procedural_envs, values, dtype, grad):
    """A policy's output is an action as it comes: any float dtype, with or without a gradient."""
    env = procedural_envs["continuous"]
    tensor = torch.tensor(values, dtype=dtype, requires_grad=grad)
    env.reset(seed=0)
    expected = env.step(tensor.detach().float().numpy())
    env.reset(seed=0)
    got = env.step(tensor)
    for key in expected[0]:
        assert np.array_equal(expected[0][key], got[0][key]), key
    assert expected[1:4] == got[1:4]


RESET_OPTIONS = st.one_of(
    NASTY,
    st.dictionaries(st.one_of(st.sampled_from(["reference", "seed", "x"]), st.integers(0, 2)), NASTY, max_size=2),
    st.builds(
        lambda v: {"reference": v}, st.one_of(NASTY, st.dictionaries(st.sampled_from(["FRONT", "lidar", "x"]), NASTY))
    ),
)


@FUZZ
@given(options=RESET_OPTIONS)
def test_reset_options_are_refused_or_reset_finite(procedural_envs, options):
    env = procedural_envs["continuous"]
    try:
        obs, _ = env.reset(seed=0, options=options)
    except (TypeError, ValueError, KeyError) as e:
        assert "reset" in str(e) or "reference" in str(e), e
        env.reset(seed=0)  # still usable
        return
    _assert_finite_inside(env, obs)


NUM_ENVS = st.one_of(st.integers(-3, 4), NASTY.filter(lambda v: not isinstance(v, int) or isinstance(v, bool)))


@settings(FUZZ, max_examples=max(EXAMPLES // 4, 10))
@given(num_envs=NUM_ENVS, config=st.one_of(st.none(), configs()))
def test_vector_args_are_refused_by_name_or_step_finite(num_envs, config):
    try:
        env = gym.make_vec("M4World-v0", num_envs=num_envs, vectorization_mode="vector_entry_point", config=config)
    except (InvalidOptionError, UnknownOptionError) as e:
        assert "num_envs" in str(e) or "config" in str(e)
        return
    try:
        obs, _ = env.reset(seed=0)
        obs, reward, *_ = env.step(env.action_space.sample())
        for key, value in obs.items():
            assert np.all(np.isfinite(value)), key
        assert np.all(np.isfinite(reward))
    finally:
        env.close()


@FUZZ
@given(track_id=NASTY, spec=st.one_of(NASTY, st.dictionaries(st.sampled_from(["id", "category", "track", "x"]), NASTY)))
def test_the_object_api_refuses_bad_ids_and_specs_by_name(procedural_envs, track_id, spec):
    env = procedural_envs["continuous"].unwrapped
    env.reset(seed=0)
    for call in (lambda: env.remove_object(track_id), lambda: env.insert_object(spec)):
        try:
            call()
        except (*REFUSALS, TypeError) as e:
            assert str(e)


@settings(FUZZ, max_examples=max(EXAMPLES // 4, 10))
@given(field=st.sampled_from([*EDITABLE, "wings"]), value=st.one_of(NASTY, st.binary(max_size=3)))
def test_object_edits_are_refused_by_field_or_within_the_bounds(procedural_envs, field, value):
    env = procedural_envs["continuous"].unwrapped
    env.reset(seed=0)
    track_id = env.bridge.object_ids()[0]
    try:
        env.edit_object(track_id, **{field: value})
    except ScenarioError as e:
        assert f"edit_object({track_id}): " in str(e) and (field in str(e) or "track" in str(e)), e
        return
    if field == "speed":
        assert _is_real(value) and 0 <= value <= bounds.MAX_SPEED_MPS
    if field == "size" and value is not None:  # None: the category's size
        assert all(_is_real(v) and bounds.MIN_OBJECT_SIZE_M <= v <= bounds.MAX_OBJECT_SIZE_M for v in value)
    assert not isinstance(value, bytes)
    obs, reward, *_ = env.step(env.action_space.sample())
    _assert_finite_inside(env, obs, reward)


def _is_real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


# ------------------------------------------------------------------------------ corrupted bundles


def _corrupt(bundle: Path, how: int, value) -> None:
    manifest_path = bundle / "manifest.json"
    if how == 0:  # flip a byte of a weight file
        f = bundle / "student.safetensors"
        data = bytearray(f.read_bytes())
        data[len(data) // 2] ^= 0xFF
        f.write_bytes(bytes(data))
    elif how == 1:  # replace a manifest field with a nasty value
        m = json.loads(manifest_path.read_text())
        paths = [p for p, _ in _paths(m)]
        path = paths[zlib.crc32(repr(value).encode()) % len(paths)]  # not hash(): it is salted per process
        cur = m
        for k in path[:-1]:
            cur = cur[k]
        new = value if not isinstance(value, float) or np.isfinite(value) else str(value)
        cur[path[-1]] = new if new != cur[path[-1]] else {"corrupt": repr(new)}  # always a change
        manifest_path.write_text(json.dumps(m))
    elif how == 2:  # truncate the manifest
        manifest_path.write_bytes(manifest_path.read_bytes()[: len(str(value)) % 200])
    elif how == 3:  # an extra JSON file beside the manifest
        (bundle / "extra.json").write_text(json.dumps({"v": str(value)}))


@settings(FUZZ, max_examples=max(EXAMPLES // 5, 10))
@given(how=st.integers(0, 3), value=NASTY)
def test_corrupted_bundles_are_refused_naming_the_file(tiny_bundle, tmp_path_factory, how, value):
    bundle = tmp_path_factory.mktemp("fuzz") / "b"
    shutil.copytree(tiny_bundle, bundle)
    _corrupt(bundle, how, value)
    with pytest.raises(CheckpointError) as err:
        load_bundle_files(bundle)
    assert str(bundle) in str(err.value)
