"""train_judge: runs end to end on a tiny dataset, is deterministic, and saves a loadable judge."""

import numpy as np
import pytest
from safetensors.numpy import load_file

from m4world_env.evalset import EvalsetConfig, record_evalset
from world_model.eval.judge import WEIGHTS_FILE, load_judge
from world_model.eval.judge_data import CollectConfig
from world_model.eval.questions import QUESTION_TYPES
from world_model.eval.train_judge import TrainJudgeConfig, main, train_judge


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("judge_data")
    cfg = EvalsetConfig(
        scenarios=(),
        short_duration=2.0,
        grid_weathers=("sunny", "rain"),
        grid_times=("day",),
        long_scenarios=(),
        base_seed=8000,
    )
    record_evalset(root, cfg, progress=False)
    return root


def _cfg() -> TrainJudgeConfig:
    return TrainJudgeConfig(
        val_every=2,
        crop_steps=3,
        scene_steps=2,
        tracks_per_batch=4,
        background_per_batch=4,
        scene_batch=2,
        collect=CollectConfig(crop_stride=4, scene_stride=10),
    )


def test_training_is_deterministic_and_saves_a_loadable_judge(data_dir, tmp_path):
    logs: list[str] = []
    a = train_judge([data_dir], tmp_path / "a", _cfg(), log=logs.append)
    train_judge([data_dir], tmp_path / "b", _cfg(), log=lambda s: None)
    wa, wb = load_file(str(tmp_path / "a" / WEIGHTS_FILE)), load_file(str(tmp_path / "b" / WEIGHTS_FILE))
    assert wa.keys() == wb.keys()
    for k in wa:
        np.testing.assert_array_equal(wa[k], wb[k])
    loaded = load_judge(tmp_path / "a")
    assert loaded.thresholds == a.thresholds
    assert set(loaded.info["validation"]) == set(QUESTION_TYPES)
    assert any("validation existence" in line for line in logs)


def test_bad_inputs_are_specific(data_dir, tmp_path):
    with pytest.raises(FileNotFoundError, match="holds no judge"):
        load_judge(tmp_path)
    with pytest.raises(ValueError, match="training and validation"):
        train_judge([data_dir], tmp_path / "x", TrainJudgeConfig(val_every=10))
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path)])  # --data is required
