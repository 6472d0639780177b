"""The env's and vector env's own arguments, refused by name before any work (observation keys,
seeds, render modes, a shared backend, object edits), and the actions a policy hands over as they
come (torch tensors, gradients and all), taken exactly as their numpy equivalents."""

import math

import gymnasium as gym
import numpy as np
import pytest
import torch

import m4world_env  # noqa: F401 (registers M4World-v0)
from m4world_env.config import InvalidOptionError
from m4world_env.env import M4WorldEnv
from m4world_env.scenario import ScenarioError

SMALL = {"height": 16, "width": 32}


def make(**kwargs):
    kwargs.setdefault("config", SMALL)
    return gym.make("M4World-v0", scenario="highway_sunny_day", **kwargs)


def make_vec(n: int = 2, **kwargs):
    kwargs.setdefault("config", SMALL)
    return gym.make_vec("M4World-v0", num_envs=n, vectorization_mode="vector_entry_point", **kwargs)


def assert_same_observations(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        assert np.array_equal(a[key], b[key]), key


@pytest.mark.parametrize("keys", [["cameras", "cameras"], ("lidar", "state", "lidar"), {"cameras": 1}, "lidar", 5])
def test_observation_keys_must_be_a_list_of_distinct_keys(keys):
    with pytest.raises(InvalidOptionError, match=r"config\.observation_keys must be .* got "):
        make(config={**SMALL, "observation_keys": keys})
    for given in (("state", "lidar"), {"state", "lidar"}):
        obs, _ = make(config={**SMALL, "observation_keys": given}).reset(seed=0)
        assert sorted(obs) == ["lidar", "state"]


@pytest.mark.parametrize("seed", [True, False, 1.5, math.nan, -1, "3", np.float64(2.0), [3]])
def test_a_single_env_seed_is_a_non_negative_integer(seed):
    env = make()
    with pytest.raises(InvalidOptionError, match=r"reset\(seed=\.\.\.\) must be a non-negative integer or None, got"):
        env.unwrapped.reset(seed=seed)


def test_numpy_integer_seeds_are_seeds():
    env = make()
    by_int, _ = env.reset(seed=7)
    by_numpy, _ = env.reset(seed=np.int64(7))
    assert_same_observations(by_int, by_numpy)


@pytest.mark.parametrize(
    "seed, match",
    [
        (True, r"a non-negative integer s \(sub-env i gets s \+ i\), a list of 2 .* got True"),
        (1.5, r"got 1\.5"),
        (math.nan, r"got nan"),
        ("ab", r"got 'ab'"),
        ({0: 1, 1: 2}, r"got \{0: 1, 1: 2\}"),
        (-1, r"must be a non-negative integer or None, got -1"),
        ([1, True], r"seed 1 must be a non-negative integer or None, got True"),
        ([1, 2.5], r"seed 1 must be .* got 2\.5"),
        ([1, 2, 3], r"needs 2 seeds, got 3"),
    ],
)
def test_a_vector_env_seed_is_an_integer_or_one_per_sub_env(seed, match):
    venv = make_vec()
    with pytest.raises(InvalidOptionError, match=r"reset\(seed=") as info:
        venv.reset(seed=seed)
    assert info.match(match)


def test_vector_seeds_may_be_numpy_integers_and_arrays():
    venv = make_vec()
    by_int, _ = venv.reset(seed=5)
    for seed in (np.int64(5), np.array([5, 6]), [np.int32(5), 6], (5, 6)):
        again, _ = venv.reset(seed=seed)
        assert_same_observations(by_int, again)


@pytest.mark.parametrize("mode", [1, ["rgb_array"], 1.5, b"rgb_array"])
def test_a_render_mode_that_is_not_a_string_is_refused_by_gym_make(mode):
    with pytest.raises(InvalidOptionError, match=r"render_mode must be one of \['rgb_array', 'rgb_array_list'\]"):
        make(render_mode=mode)
    with pytest.raises(InvalidOptionError, match="render_mode"):
        make_vec(render_mode=mode)


def test_gym_make_still_wraps_the_modes_it_knows():
    assert make(render_mode="rgb_array").render_mode == "rgb_array"
    with pytest.warns(UserWarning, match="HumanRendering"):  # gymnasium's window over rgb_array
        assert make(render_mode="human").render_mode == "human"


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"shared_backend": "x"}, r"shared_backend must be None or a sensor backend .* got str 'x'"),
        ({"shared_backend": 5}, r"shared_backend must be .* got int 5"),
        ({"backend_index": -1}, r"backend_index must be a non-negative integer, got -1"),
        ({"backend_index": True}, r"backend_index must be a non-negative integer, got True"),
        ({"backend_index": 3}, r"backend_index=3 names a rollout of a shared_backend; without one it must be 0"),
    ],
)
def test_the_vector_env_only_arguments_are_checked(kwargs, match):
    with pytest.raises(InvalidOptionError, match=match):
        M4WorldEnv("highway_sunny_day", config=SMALL, **kwargs)


def _steps(env, actions) -> list:
    env.reset(seed=3)
    return [env.step(a)[0] for a in actions]


def test_a_torch_action_is_taken_as_its_numpy_value_gradient_and_all():
    plain = [np.array([0.5, -0.25], np.float32), np.array([-1.0, 0.0], np.float32)]
    tensors = [torch.tensor(plain[0], requires_grad=True) * 1.0, torch.tensor(plain[1]).to(torch.bfloat16)]
    for expected, got in zip(_steps(make(), plain), _steps(make(), tensors), strict=True):
        assert_same_observations(expected, got)
    discrete = make(config={**SMALL, "action_type": "discrete_meta"})
    for expected, got in zip(
        _steps(discrete, [3, 1]), _steps(discrete, [torch.tensor(3), torch.tensor([1])]), strict=True
    ):
        assert_same_observations(expected, got)


def test_a_vector_env_takes_torch_actions_too():
    venv = make_vec()
    actions = np.array([[0.5, 0.0], [-0.5, 0.1]], np.float32)
    venv.reset(seed=1)
    expected = venv.step(actions)[0]
    venv.reset(seed=1)
    assert_same_observations(expected, venv.step(torch.tensor(actions, requires_grad=True))[0])
    venv.reset(seed=1)
    assert_same_observations(expected, venv.step([torch.tensor(a, requires_grad=True) for a in actions])[0])


@pytest.mark.parametrize(
    "changes, match",
    [
        ({"speed": 1e300}, r"speed: must be a number in \[0, 90\] m/s, got 1e\+300"),
        ({"speed": True}, r"speed: must be a number .* got True"),
        ({"speed": "5"}, r"speed: must be a number .* got '5'"),
        ({"speed": math.nan}, r"speed: must be a number .* got nan"),
        ({"size": [1e-300, 1e-300, 1e-300]}, r"size: Value error, size must be three lengths in \[0\.05, 30\] m"),
        ({"description": b"a red car"}, r"description: Input should be a valid string, got b'a red car'"),
        ({"wings": 2}, r"cannot edit \['wings'\]"),
    ],
)
def test_object_edits_are_refused_by_field_and_value_and_change_nothing(changes, match):
    env = make().unwrapped
    env.reset(seed=0)
    car = env.bridge.object_ids()[0]
    with pytest.raises(ScenarioError, match=rf"^edit_object\({car}\): {match}"):
        env.edit_object(car, color="green", **changes)
    after = next(o for o in env.bridge.step([0.0, 0.0])[-1].objects if o.track_id == car)
    assert after.color_name != "green"  # the colour given beside the bad field was not applied
    env.edit_object(car, speed=np.float32(12.5))  # a numpy number is a number
