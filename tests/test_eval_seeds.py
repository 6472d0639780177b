"""Model rows average over noise seeds: every score is the mean, with its spread."""

import pytest

from world_model.eval.report import GenerationScores, LongHorizon, RowScores, YesFrequencies
from world_model.eval.report.seeds import average_seeds


def result(psnr, tod_views, mae, curve=(20.0, 10.0)):
    return RowScores(
        table1=GenerationScores(psnr_db=psnr, lidar_range_mae_m=mae),
        table2=YesFrequencies(time_of_day=sum(tod_views) / len(tod_views)),
        per_view={"time_of_day": tuple(tod_views)},
        answers=12,
        long_horizon=(LongHorizon("long_a", 2, curve, curve[-1] / curve[0]),),
    )


def test_scores_are_averaged_with_their_spread():
    row = average_seeds(
        [result(20.0, [1.0, 0.0], 2.0), result(22.0, [1.0, 1.0], None), result(24.0, [0.0, 1.0], 4.0, (30.0, 30.0))]
    )
    assert row.seeds == 3
    assert row.table1.psnr_db == pytest.approx(22.0)
    assert row.spread.table1.psnr_db == pytest.approx((8 / 3) ** 0.5)
    assert row.table1.lidar_range_mae_m is None  # missing in one seed: not averaged over the others
    assert row.table1.frechet_judge_clip is None and row.spread.table1.frechet_judge_clip is None
    assert row.per_view["time_of_day"] == pytest.approx([2 / 3, 2 / 3])
    assert row.spread.per_view["time_of_day"] == pytest.approx([(2 / 9) ** 0.5] * 2)
    assert row.table2.time_of_day == pytest.approx(2 / 3) and row.table2.existence is None
    assert row.answers == 12 and isinstance(row.answers, int)  # a count every seed shares stays a count
    (long,) = row.long_horizon
    assert long.clip == "long_a" and long.seconds == 2
    assert long.psnr_per_second == pytest.approx([70 / 3, 50 / 3]) and long.ratio_last_first == pytest.approx(2 / 3)
    data = row.to_json()
    assert data["seeds"] == 3 and set(data["spread"]) == {"table1", "table2", "per_view"}


def test_one_seed_has_no_spread():
    row = average_seeds([result(20.0, [1.0], 1.0)])
    assert row.table1.psnr_db == 20.0 and row.spread.table1.psnr_db == 0.0


def test_no_seed_is_refused():
    with pytest.raises(ValueError, match="at least one"):
        average_seeds([])
