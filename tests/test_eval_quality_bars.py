"""The report's quality bars: each bar's pass/fail and the autoencoder row as the ceiling."""

from world_model.eval.report import (
    GenerationScores,
    LongHorizon,
    QualityBars,
    Report,
    RowScores,
    WindowFrechet,
    YesFrequencies,
    check_bars,
)
from world_model.eval.report.markdown import existence_by_category, quality_bars


def _row(lidar_first_s=1.5, long_horizon=(), **yes):
    t2 = YesFrequencies(**(dict.fromkeys(YesFrequencies().to_json(), 0.5) | yes))
    return RowScores(GenerationScores(lidar_range_mae_first_s_m=lidar_first_s), t2, long_horizon=long_horizon)


def _report(**rows):
    return Report(rows, clips=())


def _check(checks, bar):
    (check,) = [c for c in checks if c.bar.startswith(bar)]
    return check


def test_bars_against_oracle_baseline_and_autoencoder_ceiling():
    rows = {
        "oracle": _row(existence=1.0, weather=1.0),
        "autoencoder": _row(existence=0.7, weather=0.99, visual_fidelity=0.7),
        "geometry_only": _row(visual_fidelity=0.2),
        "student": _row(existence=0.85, weather=0.5, visual_fidelity=0.6),
    }
    checks = check_bars(_report(**rows))
    existence = _check(checks, "existence ≥ 0.8 x oracle")
    assert existence.met and existence.ceiling.endswith("out of reach")  # 0.7 x: the VAE's ceiling misses it
    weather = _check(checks, "weather ≥ 0.85 x oracle")
    assert weather.status == "missed" and weather.ceiling.endswith(": reachable")
    visual = _check(checks, "visual_fidelity ≥ geometry_only + 0.30")
    assert visual.measured == "0.600 - 0.200 = 0.400" and visual.met and visual.ceiling.endswith(": reachable")
    assert _check(checks, "cross_view_consistency > geometry_only").ceiling == ""  # blur does not cap consistency
    assert _check(checks, "LiDAR range MAE first second ≤ 2.0 m").met
    # Without the ceiling row the column stays empty; without a baseline the margins are unmeasured.
    del rows["autoencoder"], rows["geometry_only"]
    checks = check_bars(_report(**rows))
    assert _check(checks, "existence ≥ 0.8 x oracle").ceiling == ""
    assert _check(checks, "visual_fidelity ≥ geometry_only + 0.30").status == "not measured"
    assert check_bars(_report(student=_row())) == []  # no Oracle: no bars


def test_thresholds_decide_pass_or_fail():
    rows = {"oracle": _row(existence=1.0), "student": _row(existence=0.85, lidar_first_s=2.5)}
    assert _check(check_bars(_report(**rows)), "existence ≥ 0.8").met
    strict = QualityBars(oracle_ratios=(("existence", 0.9),), lidar_first_s_max_m=3.0)
    checks = check_bars(_report(**rows), bars=strict)
    assert _check(checks, "existence ≥ 0.9 x oracle").status == "missed"
    assert _check(checks, "LiDAR range MAE first second ≤ 3.0 m").met
    assert not _check(check_bars(_report(**rows)), "LiDAR range MAE first second ≤ 2.0 m").met
    rows["student"] = _row(lidar_first_s=None)
    assert _check(check_bars(_report(**rows)), "LiDAR range MAE").status == "not measured"


def test_long_horizon_bar_needs_psnr_and_frechet_within_tolerance():
    def clip(name, psnr_ratio, frechet_ratio):
        return LongHorizon(name, 60, (20.0,) * 60, psnr_ratio, WindowFrechet(1.0, frechet_ratio, frechet_ratio))

    long = (clip("long_a", 0.9, 1.1), clip("long_b", 0.75, 1.0), clip("long_c", 1.0, 1.3))
    checks = check_bars(_report(oracle=_row(), student=_row(long_horizon=long)))
    assert [_check(checks, c).met for c in ("long_a", "long_b", "long_c")] == [True, False, False]
    assert _check(checks, "long_a").measured == "0.900, 1.100"


def test_bars_table_lines():
    lines = quality_bars(_report(oracle=_row(existence=1.0), student=_row(existence=0.85)))
    assert lines[1] == "### Quality bars (student)"
    assert "| existence ≥ 0.8 x oracle | 0.850 / 1.000 = 0.850 x | met |  |" in lines
    assert quality_bars(_report(student=_row())) == []


def test_existence_by_category_table_lists_every_judged_category_per_row():
    rows = {
        "oracle": RowScores(per_category={"existence": {"car": 1.0, "tree_truck": 0.9}}),
        "student": RowScores(per_category={"existence": {"car": 0.25}}),  # never judged a truck
        "student_adapted": RowScores(per_category={"existence": {"car": 0.25, "tree_truck": 0.5}}),
    }
    lines = existence_by_category(_report(**rows))
    assert "| row | car | tree_truck |" in lines
    assert "| student | 0.250 | n/a |" in lines and "| student_adapted | 0.250 | 0.500 |" in lines
    assert existence_by_category(_report(student=RowScores())) == []


def test_absolute_and_per_view_bars():
    student = _row(existence=0.55)
    per_view = {"time_of_day": (1.0, 0.95, 0.4, 1.0), "weather": (0.9, 0.85, 0.8, None)}
    rows = {
        "oracle": _row(existence=1.0),
        "autoencoder": RowScores(per_view={"time_of_day": (1.0,) * 4, "weather": (0.9, 0.7, 0.9, 0.9)}),
        "student": RowScores(student.table1, student.table2, per_view=per_view),
    }
    checks = check_bars(_report(**rows))
    assert _check(checks, "existence ≥ 0.6").status == "missed"
    time_of_day = _check(checks, "time_of_day ≥ 0.9 in every camera view")
    assert time_of_day.measured == "0.400 (view 2)" and time_of_day.met is False
    assert time_of_day.ceiling == "1.000 (view 0): reachable"
    weather = _check(checks, "weather ≥ 0.8 in every camera view")
    assert weather.met and weather.ceiling.endswith("out of reach")  # the VAE's view 1 says 0.7
    rows["student"] = _row()  # no per-view answers: not measured
    assert _check(check_bars(_report(**rows)), "weather ≥ 0.8 in every camera view").status == "not measured"
