"""Every kind of bad input a careless user gives is refused early, by name — never a hang, an
internal crash, or a silently wrong episode."""

import json
import math
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import yaml

import m4world_env  # noqa: F401 (registers M4World-v0)
from m4world_env.config import InvalidOptionError, UnknownOptionError
from m4world_env.scenario import SCENARIOS_DIR, ScenarioError, load_scenario
from m4world_env.traffic import ActionError
from m4world_env.traffic.population import UnknownObjectError
from world_model.bundle import CheckpointError, load_bundle_files, reseal_bundle
from world_model.lora import AdapterError, read_adapter

ROOT = Path(__file__).resolve().parents[1]
SMALL = {"height": 16, "width": 32}


def _base() -> dict:
    return yaml.safe_load((SCENARIOS_DIR / "highway_sunny_day.yaml").read_text())


def _write(tmp_path: Path, data: object, name: str = "s.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data) if not isinstance(data, str) else data)
    return p


def _with(path: str, value: object) -> dict:
    data = _base()
    cur = data
    *parents, last = path.split(".")
    for key in parents:
        cur = cur.setdefault(key, {})
    cur[last] = value
    return data


def make(**kwargs):
    kwargs.setdefault("config", SMALL)
    return gym.make("M4World-v0", scenario="highway_sunny_day", **kwargs)


# ------------------------------------------------------------------------------ scenario files


@pytest.mark.parametrize(
    "field, value",
    [
        ("policy_frequency", 1.0e-300),  # frames per step unbounded: a step would never return
        ("sensor_frequency", 1.0e6),
        ("road.length", 1.0e7),  # reset would build a road for minutes
        ("duration", 1.0e300),
        ("ego.speed", 1.0e300),
        ("ego.longitudinal", 1.0e30),
        ("road.lane_width", 1.0e9),
    ],
)
def test_absurd_magnitudes_are_refused_at_load_naming_the_field(tmp_path, field, value):
    with pytest.raises(ScenarioError, match=field.replace(".", r"\.")):
        load_scenario(_write(tmp_path, _with(field, value)))


def test_a_huge_object_and_far_away_positions_are_refused(tmp_path):
    data = _base()
    data["objects"] = [
        {"id": "x", "category": "car", "size": [1e300, 2, 2], "track": {"kind": "static", "x": 1e300, "y": 0}}
    ]
    with pytest.raises(ScenarioError, match=r"objects\.0\.(size|track\.x)"):
        load_scenario(_write(tmp_path, data))


def test_yaml_booleans_are_not_numbers(tmp_path):
    for field in ("road.lanes", "duration", "ego.speed"):
        text = yaml.safe_dump(_with(field, True)).replace(": true", ": yes")  # YAML 1.1 reads yes as true
        with pytest.raises(ScenarioError, match=field.replace(".", r"\.")):
            load_scenario(_write(tmp_path, text))


def test_duplicate_yaml_keys_are_refused(tmp_path):
    with pytest.raises(ScenarioError, match="duplicate key 'duration'"):
        load_scenario(_write(tmp_path, "name: x\nroad: {type: highway}\nduration: 10\nduration: 20\n"))


def test_a_file_that_is_not_utf8_is_refused(tmp_path):
    p = tmp_path / "latin1.yaml"
    p.write_bytes("name: caf\xe9\nroad: {type: highway}\n".encode("latin-1"))
    with pytest.raises(ScenarioError, match="not UTF-8"):
        load_scenario(p)


def test_yaml_nested_hundreds_deep_is_refused(tmp_path):
    with pytest.raises(ScenarioError, match="nested|road"):
        load_scenario(_write(tmp_path, "name: x\nroad: " + "[" * 600 + "]" * 600 + "\n"))


def test_a_directory_or_a_non_path_is_not_a_scenario(tmp_path):
    (tmp_path / "d.yaml").mkdir()
    with pytest.raises(ScenarioError, match="directory"):
        load_scenario(tmp_path / "d.yaml")
    with pytest.raises(ScenarioError, match="int"):
        load_scenario(5)
    with pytest.raises(ScenarioError):
        gym.make("M4World-v0", scenario=5)


def test_scenarios_check_builds_what_reset_builds(tmp_path):
    ok = _write(tmp_path, _base(), "ok.yaml")
    bad = _write(tmp_path, _with("road.length", 1.0e7), "bad.yaml")
    cli = [sys.executable, "-m", "m4world_env.cli", "scenarios", "--check"]
    assert subprocess.run([*cli, str(ok)], capture_output=True, text=True).returncode == 0
    out = subprocess.run([*cli, str(bad)], capture_output=True, text=True)
    assert out.returncode == 2 and "road.length" in out.stderr and "Traceback" not in out.stderr


# ---------------------------------------------------------------------------------- env config


@pytest.mark.parametrize("config", [[], 0, "", "abc"])
def test_a_config_that_is_not_a_dict_is_refused(config):
    with pytest.raises(InvalidOptionError, match="config must be a dict"):
        make(config=config)


@pytest.mark.parametrize(
    "config, match",
    [
        ({"height": 1}, r"config\.height"),
        ({"state_objects": 10**7}, r"config\.state_objects"),
        ({"reward": {"collision": -1e308}}, r"config\.reward\.collision"),
        ({"reward": {"high_speed": 1e308}}, r"config\.reward\.high_speed"),
        ({"reward": {"speed_range": [0, 1e9]}}, r"config\.reward\.speed_range"),
        ({"model": {"denoising_steps": 10**9}}, r"config\.model\.denoising_steps"),
        ({"model": {"sink_frames": 10**6}}, r"config\.model\.sink_frames"),
        ({"model": {"device": "mps"}}, r"config\.model\.device"),
        ({"model": {"device": "meta"}}, r"config\.model\.device"),
        ({"model": {"rollout_threads": 0}}, r"config\.model\.rollout_threads"),
        ({"model": {"rollout_threads": 10**6}}, r"config\.model\.rollout_threads"),
        ({"model": {"rollout_threads": 1.5}}, r"config\.model\.rollout_threads"),
        ({"model": {"rollout_threads": True}}, r"config\.model\.rollout_threads"),
        ({"model": {"rollout_threads": "2"}}, r"config\.model\.rollout_threads"),
    ],
)
def test_out_of_bounds_options_are_refused_by_name(config, match):
    with pytest.raises(InvalidOptionError, match=match):
        make(config=config)


def test_non_string_config_keys_are_refused():
    with pytest.raises(UnknownOptionError, match="must be strings"):
        make(config={1: 2})


def test_render_mode_must_be_a_known_mode():
    from m4world_env.env import M4WorldEnv

    for mode in (1, "human", "rgb"):
        with pytest.raises(InvalidOptionError, match="render_mode"):
            M4WorldEnv(scenario="highway_sunny_day", render_mode=mode, config=SMALL)


# ----------------------------------------------------------------------- actions, reset, objects


@pytest.mark.parametrize(
    "action",
    [
        ["0.5", "0"],
        [True, False],
        np.array([0.5 + 1j, 0.0]),
        np.array(["2020-01-01", "2020-01-02"], "datetime64[D]"),
        [10**400, 0],
        "fast",
        None,
    ],
)
def test_actions_must_be_two_real_numbers(action):
    env = make()
    env.reset(seed=0)
    with pytest.raises(ActionError, match="continuous action"):
        env.step(action)
    env.step([0.0, 0.0])  # still usable


def test_reset_options_must_be_a_dict_and_references_a_dict_of_views():
    env = make()
    with pytest.raises(TypeError, match="reset options must be a dict"):
        env.reset(options="abc")
    with pytest.raises(TypeError, match="'reference' must be a dict"):
        env.reset(options={"reference": np.zeros((16, 32, 3), np.uint8)})
    env.reset(seed=0)


def test_objects_are_named_by_string_ids():
    env = make()
    env.reset(seed=0)
    with pytest.raises(UnknownObjectError, match="string"):
        env.unwrapped.remove_object(["id"])


@pytest.mark.parametrize("num_envs", ["3", 1.5, None, 0, True, 10**9])
def test_vector_env_size_must_be_a_positive_integer(num_envs):
    with pytest.raises(InvalidOptionError, match="num_envs"):
        gym.make_vec("M4World-v0", num_envs=num_envs, vectorization_mode="vector_entry_point", config=SMALL)


# ------------------------------------------------------------------ world model: references, bundles


@pytest.mark.parametrize("bad", [np.nan, np.inf, -50.0, 1e30])
def test_lidar_references_must_be_finite_ranges(tiny_bundle, bad):
    env = gym.make("M4World-v0", scenario="highway_sunny_day", backend="world_model", checkpoint=str(tiny_bundle))
    spec = env.unwrapped.backend.wm.cfg.sensors.lidar
    ranges = np.full((spec.beams, spec.azimuth), 20.0, np.float32)
    ranges[0, 0] = bad
    with pytest.raises(ValueError, match="reference 'lidar'"):
        env.reset(seed=0, options={"reference": {"lidar": ranges}})
    obs, _ = env.reset(seed=0)
    assert np.isfinite(obs["lidar"]).all()


def _copy_bundle(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def test_nan_weights_are_refused_even_with_a_rehashed_manifest(tiny_bundle, tmp_path):
    from safetensors.torch import load_file, save_file

    b = _copy_bundle(tiny_bundle, tmp_path / "b")
    state = load_file(str(b / "student.safetensors"))
    key = next(k for k, v in state.items() if v.is_floating_point())
    state[key] = state[key] * float("nan")
    save_file(state, str(b / "student.safetensors"))
    reseal_bundle(b)
    with pytest.raises(CheckpointError, match="non-finite"):
        load_bundle_files(b)


def _edit_manifest(bundle: Path, edit) -> None:
    manifest = json.loads((bundle / "manifest.json").read_text())
    edit(manifest)
    (bundle / "manifest.json").write_text(json.dumps(manifest))


def test_the_manifest_digest_covers_the_configs(tiny_bundle, tmp_path):
    b = _copy_bundle(tiny_bundle, tmp_path / "b")
    _edit_manifest(b, lambda m: m["model_config"]["sensors"].update(height=32))
    with pytest.raises(CheckpointError, match="digest"):
        load_bundle_files(b)
    (b / "streaming.json").write_text("{}")  # any config file beside the manifest is covered too
    b2 = _copy_bundle(tiny_bundle, tmp_path / "b2")
    (b2 / "extra.json").write_text("{}")
    with pytest.raises(CheckpointError, match="digest"):
        load_bundle_files(b2)


def test_unknown_config_keys_and_components_are_refused(tiny_bundle, tmp_path):
    from world_model.rollout.runtime import load_world_model

    b = _copy_bundle(tiny_bundle, tmp_path / "b")
    _edit_manifest(b, lambda m: m["model_config"]["dit"].update(secret_knob=3))
    reseal_bundle(b)
    with pytest.raises(CheckpointError, match="secret_knob"):
        load_world_model(b)
    b2 = _copy_bundle(tiny_bundle, tmp_path / "b2")
    _edit_manifest(b2, lambda m: m["components"].update(extra=dict(m["components"]["vae"])))
    with pytest.raises(CheckpointError, match="unknown component"):
        load_bundle_files(b2)


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda m: m["components"]["vae"].update(file=5), "'file' must be a file name"),
        (lambda m: m["components"]["vae"].update(file="../vae.safetensors"), "'file' must be a file name"),
        (lambda m: m["model_config"]["dit"].update(heads=0), "heads"),
    ],
)
def test_corrupt_manifest_fields_are_named(tiny_bundle, tmp_path, edit, match):
    from world_model.rollout.runtime import load_world_model

    b = _copy_bundle(tiny_bundle, tmp_path / "b")
    _edit_manifest(b, edit)
    if "heads" in match:
        reseal_bundle(b)
    with pytest.raises(CheckpointError, match=match):
        load_world_model(b)


def test_a_manifest_that_is_not_utf8_and_a_checkpoint_that_is_not_a_path(tiny_bundle, tmp_path):
    b = _copy_bundle(tiny_bundle, tmp_path / "b")
    (b / "manifest.json").write_bytes(b"\xff\xfe{")
    with pytest.raises(CheckpointError, match="manifest.json is corrupt"):
        load_bundle_files(b)
    with pytest.raises(CheckpointError, match="must be a path"):
        load_bundle_files(5)


def test_adapters_carry_a_checksum_and_a_corrupt_one_is_named(tmp_path):
    import shutil

    from world_model.bundle import DEFAULT_BUNDLE

    a = tmp_path / "tree_truck_completion"
    shutil.copytree(DEFAULT_BUNDLE / "adapters" / "tree_truck_completion", a)
    read_adapter(a)
    data = bytearray((a / "adapter.safetensors").read_bytes())
    data[-1] ^= 0xFF
    (a / "adapter.safetensors").write_bytes(bytes(data))
    with pytest.raises(AdapterError, match="adapter.safetensors does not match"):
        read_adapter(a)
    (a / "adapter.json").write_text("{broken")
    with pytest.raises(AdapterError, match="adapter.json is corrupt"):
        read_adapter(a)


# ------------------------------------------------------------------------------------------ CLI


def _cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "m4world_env.cli", *args], capture_output=True, text=True, cwd=cwd)


@pytest.mark.parametrize(
    "args, match",
    [
        (["eval", "--max-steps", "0"], "--max-steps"),
        (["train", "--stage", "vae", "--batch-size", "0"], "--batch-size"),
        (["record", "--scenario", "highway_sunny_day", "--episodes", "0", "--out", "x"], "--episodes"),
        (["eval", "--policy", "math:pi", "--scenarios", "highway_sunny_day", "--max-steps", "1"], "not a callable"),
    ],
)
def test_cli_mistakes_are_one_error_line(args, match):
    out = _cli(*args)
    assert out.returncode == 2, out.stderr
    assert match in out.stderr and "Traceback" not in out.stderr


def test_cli_outputs_are_checked_before_any_work(tmp_path):
    out = _cli("eval", "--scenarios", "highway_sunny_day", "--out", str(tmp_path))
    assert out.returncode == 2 and "is a directory" in out.stderr
    file = tmp_path / "f"
    file.write_text("x")
    out = _cli("record", "--scenario", "highway_sunny_day", "--out", str(file))
    assert out.returncode == 2 and "is a file" in out.stderr


def test_an_empty_checkpoint_pointer_is_named(tmp_path):
    from world_model.train.checkpoint import load_latest

    (tmp_path / "latest.json").write_text("")
    with pytest.raises(ValueError, match="latest.json is corrupt"):
        load_latest(tmp_path)


def test_reward_is_finite_at_the_bounds():
    env = make(config={**SMALL, "reward": {"collision": -1e3, "high_speed": 1e3, "normalize": False}})
    env.reset(seed=0)
    for _ in range(3):
        _, reward, *_ = env.step([1.0, 0.0])
        assert math.isfinite(reward)
