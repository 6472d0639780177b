"""Property-based fuzzing through the public interface: every input either raises one of the
project's exceptions, with a message that names what was wrong, or gives an env whose observations
and rewards are finite and inside its spaces. Never an internal crash, a hang or a NaN.

Derandomized (hypothesis' database off, a fixed example stream), so CI sees the same cases
every run; ``FUZZ_EXAMPLES`` scales the number of cases per property.
"""

import copy
import json
import os
import shutil
import zlib
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import m4world_env  # noqa: F401 (registers M4World-v0)
from m4world_env.config import InvalidOptionError, UnknownOptionError
from m4world_env.scenario import SCENARIOS_DIR, ScenarioError, scenario_from_dict
from m4world_env.traffic import ActionError
from m4world_env.traffic.population import UnknownObjectError
from world_model.bundle import CheckpointError, load_bundle_files

EXAMPLES = int(os.environ.get("FUZZ_EXAMPLES", "200"))
FUZZ = settings(
    max_examples=EXAMPLES,
    derandomize=True,
    database=None,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
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
            cur[path[-1]] = draw(NASTY)
        elif isinstance(cur, dict):
            del cur[path[-1]]
    return data


@FUZZ
@given(mutated_scenarios())
def test_mutated_scenarios_are_refused_by_field_or_run_finite(data):
    try:
        scenario = scenario_from_dict(data, "fuzz.yaml")
    except ScenarioError as e:
        assert "fuzz.yaml" in str(e)
        return
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


ACTIONS = st.one_of(
    NASTY,
    st.lists(NASTY, min_size=0, max_size=3),
    st.lists(st.floats(-2, 2), min_size=2, max_size=2),
    st.sampled_from(
        [np.array([0.5 + 1j, 0]), np.array(["a", "b"]), np.array([True, False]), np.zeros((2, 1)), np.zeros(2, "M8[s]")]
    ),
)


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
