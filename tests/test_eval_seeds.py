"""Model rows average over noise seeds: every score is the mean, with its spread."""

import pytest

from world_model.eval.report import average_seeds


def result(psnr, tod_views, mae):
    return {
        "table1": {"psnr": psnr, "lidar_mae_m": mae, "frechet_judge_clip": None},
        "table2": {"time_of_day": sum(tod_views) / len(tod_views)},
        "per_view": {"time_of_day": tod_views},
        "answers": 12,
        "long_horizon": [],
    }


def test_scores_are_averaged_with_their_spread():
    row = average_seeds([result(20.0, [1.0, 0.0], 2.0), result(22.0, [1.0, 1.0], None), result(24.0, [0.0, 1.0], 4.0)])
    assert row["seeds"] == 3
    assert row["table1"]["psnr"] == pytest.approx(22.0)
    assert row["spread"]["table1"]["psnr"] == pytest.approx((8 / 3) ** 0.5)
    assert row["table1"]["lidar_mae_m"] is None  # missing in one seed: not averaged over the others
    assert row["table1"]["frechet_judge_clip"] is None
    assert row["per_view"]["time_of_day"] == pytest.approx([2 / 3, 2 / 3])
    assert row["spread"]["per_view"]["time_of_day"] == pytest.approx([(2 / 9) ** 0.5] * 2)
    assert row["table2"]["time_of_day"] == pytest.approx(2 / 3)
    assert row["answers"] == 12


def test_one_seed_has_no_spread():
    row = average_seeds([result(20.0, [1.0], 1.0)])
    assert row["table1"]["psnr"] == 20.0 and row["spread"]["table1"]["psnr"] == 0.0


def test_no_seed_is_refused():
    with pytest.raises(ValueError, match="at least one"):
        average_seeds([])
