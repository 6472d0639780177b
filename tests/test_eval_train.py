"""train_judge: runs end to end on a tiny dataset, is deterministic, saves a loadable judge, keeps a
given judge's object network when asked, and asks weather and time of day of single views."""

from dataclasses import replace

import numpy as np
import pytest
from safetensors.numpy import load_file

from m4world_env.evalset import EvalsetConfig, record_evalset
from world_model.eval.judge import WEIGHTS_FILE, load_judge
from world_model.eval.judge_data import CollectConfig, JudgeData
from world_model.eval.questions import QUESTION_TYPES, build_questions
from world_model.eval.train_judge import TrainJudgeConfig, main, train_judge
from world_model.scene import WEATHERS


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


def test_keeping_the_crop_net_trains_only_the_scene_net_and_asks_each_view(data_dir, tmp_path):
    base = train_judge([data_dir], tmp_path / "base", _cfg(), log=lambda s: None)
    cfg = replace(_cfg(), seed=1)  # another scene net
    judge = train_judge([data_dir], tmp_path / "kept", cfg, log=lambda s: None, keep_crop_net=tmp_path / "base")
    wa, wb = load_file(str(tmp_path / "base" / WEIGHTS_FILE)), load_file(str(tmp_path / "kept" / WEIGHTS_FILE))
    crop = [k for k in wa if k.startswith("crop.")]
    assert crop and all(np.array_equal(wa[k], wb[k]) for k in crop)
    assert any(not np.array_equal(wa[k], wb[k]) for k in wa if k.startswith("scene."))
    object_thresholds = ("category", "color", "clarity", "visual_fidelity", "consistency")
    assert all(getattr(judge.thresholds, t) == getattr(base.thresholds, t) for t in object_thresholds)
    assert judge.info["crop_net_from"]["train_clips"] == base.info["train_clips"]
    views = load_judge(tmp_path / "kept").info["validation"]["weather"]["per_category"]
    assert sorted(views) == [f"view {k}" for k in range(6)]  # scene questions are asked view by view


def test_scene_questions_are_single_views_labelled_with_their_frame():
    frames = np.random.default_rng(0).integers(0, 255, (3, 6, 8, 12, 3), dtype=np.uint8)
    data = JudgeData(scene_frames=list(frames), weather=[0, 1, 2], time_of_day=[0, 1, 2])
    q = build_questions(data, seed=0)["weather"]
    assert q.a.shape == (2 * 3 * 6, 1, 8, 12, 3)
    np.testing.assert_array_equal(q.a[7, 0], frames[1, 1])  # frame 1, view 1
    assert q.asked[7] == WEATHERS[1] and q.label[7] and q.group[7] == "view 1"
    assert not q.label[3 * 6 + 7] and q.asked[3 * 6 + 7] != WEATHERS[1]  # the same view asked a wrong weather
