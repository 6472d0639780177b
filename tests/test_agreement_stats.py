"""The agreement statistics on hand-worked cases, and the summary, report and plot built from them."""

import json
import math

import numpy as np
import pytest

from m4world_env.agreement.plot import scatter_plot
from m4world_env.agreement.render import RunHeader, build_summary, markdown_report
from m4world_env.agreement.stats import (
    MODEL,
    TRUTH,
    agreement,
    agreement_by_scenario,
    agreement_intervals,
    bootstrap_mean_ci,
    episode_key,
    kendall_tau,
    mmrv,
    most_disagreeing,
    paired_episodes,
    pearson,
    policy_scores,
    spearman,
)


def record(policy, scenario, seed, backend, pdms, collision=0, **extra):
    return {
        "policy": policy,
        "family": "modular",
        "scenario": scenario,
        "seed": seed,
        "backend": backend,
        "pdms": pdms,
        "collision": collision,
        "off_road": 0,
        "progress": pdms,
        "ttc_violation": 0,
        "comfort": 1,
        "steps": 10,
        **extra,
    }


# --- correlations -------------------------------------------------------------------------------


def test_correlations_of_one_swapped_pair():
    # x = [1, 2, 3, 4], y = [1, 3, 2, 4]: deviations (-1.5, -0.5, 0.5, 1.5) and (-1.5, 0.5, -0.5, 1.5),
    # sum of products 2.25 - 0.25 - 0.25 + 2.25 = 4, sums of squares 5 and 5: r = 4 / 5.
    # The values are their own ranks: rho = r. Of the 6 pairs only (2, 3) is discordant: tau = (5 - 1) / 6.
    x, y = [1, 2, 3, 4], [1, 3, 2, 4]
    assert pearson(x, y) == pytest.approx(0.8)
    assert spearman(x, y) == pytest.approx(0.8)
    assert kendall_tau(x, y) == pytest.approx(2 / 3)


def test_spearman_gives_ties_their_average_rank():
    # ranks of [1, 2, 2, 10] are [1, 2.5, 2.5, 4] (the outlier counts as rank 4 only); against
    # [1, 2, 3, 4]: deviations (-1.5, 0, 0, 1.5) and (-1.5, -0.5, 0.5, 1.5), products sum 4.5,
    # squares 4.5 and 5: rho = 4.5 / sqrt(22.5) = 3 / sqrt(10).
    assert spearman([1, 2, 2, 10], [1, 2, 3, 4]) == pytest.approx(3 / math.sqrt(10))
    assert pearson([1, 2, 2, 10], [1, 2, 3, 4]) != pytest.approx(3 / math.sqrt(10))


def test_kendall_tau_b_corrects_for_ties():
    # x = [1, 2, 2, 3], y = [1, 2, 3, 4]: of n0 = 6 pairs, 5 concordant, 0 discordant, 1 tied in x
    # (the pair of 2s), none tied in y: tau_b = 5 / sqrt((6 - 1) * (6 - 0)) = 5 / sqrt(30).
    assert kendall_tau([1, 2, 2, 3], [1, 2, 3, 4]) == pytest.approx(5 / math.sqrt(30))


def test_a_reversed_ranking_is_perfectly_anticorrelated():
    x, y = [0.1, 0.5, 0.9], [0.9, 0.5, 0.1]
    assert pearson(x, y) == pytest.approx(-1.0)
    assert spearman(x, y) == pytest.approx(-1.0)
    assert kendall_tau(x, y) == pytest.approx(-1.0)


def test_correlations_are_scipys_with_ties():
    from scipy import stats as scipy_stats

    rng = np.random.default_rng(0)
    for _ in range(20):
        x, y = rng.integers(0, 6, 12) / 5, rng.integers(0, 6, 12) / 5  # scores with ties
        assert pearson(x, y) == pytest.approx(scipy_stats.pearsonr(x, y).statistic, abs=1e-12)
        assert spearman(x, y) == pytest.approx(scipy_stats.spearmanr(x, y).statistic, abs=1e-12)
        assert kendall_tau(x, y) == pytest.approx(scipy_stats.kendalltau(x, y, variant="b").statistic, abs=1e-12)


def test_a_correlation_with_a_constant_side_is_nan():
    for f in (pearson, spearman, kendall_tau):
        assert math.isnan(f([0.5, 0.5, 0.5], [0.1, 0.2, 0.3]))
        assert math.isnan(f([0.1, 0.2, 0.3], [0.7, 0.7, 0.7]))
        assert math.isnan(f([0.4], [0.6]))  # one policy: no spread on either side


def test_correlations_refuse_mismatched_or_broken_input():
    with pytest.raises(ValueError, match="equal length"):
        pearson([1, 2, 3], [1, 2])
    with pytest.raises(ValueError, match="finite"):
        spearman([1, 2, float("nan")], [1, 2, 3])
    with pytest.raises(ValueError, match="at least one"):
        kendall_tau([], [])


# --- MMRV ---------------------------------------------------------------------------------------


def test_mmrv_worked_three_policy_example():
    # real = [0.9, 0.5, 0.1], sim = [0.4, 0.6, 0.1]; violation when (sim_i > sim_j) != (real_i > real_j):
    #   i=0: j=1: sim 0.4 > 0.6 no, real 0.9 > 0.5 yes -> |0.9 - 0.5| = 0.4; j=2: both yes -> 0.  max 0.4
    #   i=1: j=0: sim 0.6 > 0.4 yes, real 0.5 > 0.9 no -> 0.4;              j=2: both yes -> 0.  max 0.4
    #   i=2: j=0, j=1: both "no" on both sides -> 0.                                             max 0
    # MMRV = (0.4 + 0.4 + 0) / 3 = 0.8 / 3.
    assert mmrv([0.9, 0.5, 0.1], [0.4, 0.6, 0.1]) == pytest.approx(0.8 / 3)


def test_mmrv_is_zero_for_identical_rankings():
    real = [0.9, 0.5, 0.1, 0.7]
    assert mmrv(real, real) == 0.0
    assert mmrv(real, [v**2 - 3 for v in real]) == 0.0  # any increasing map keeps the ranking
    assert mmrv([0.3], [0.8]) == 0.0


def test_mmrv_of_a_reversed_ranking():
    # real = [0.1, 0.5, 0.9], sim reversed: every pair is violated; each policy's worst partner is
    # the farthest one: 0.8, 0.4, 0.8 -> 2 / 3.
    assert mmrv([0.1, 0.5, 0.9], [0.9, 0.5, 0.1]) == pytest.approx(2 / 3)


def test_mmrv_charges_a_simulator_tie_to_the_policy_the_truth_ranks_higher():
    # SIMPLER's reference code: real = [0.5, 0, 0.75, 0.5], sim = [2/3, 0, 0, 2/3] (policies 1 and 2
    # tied in sim, 0 and 3 tied on both sides):
    #   i=0: j=2: sim yes, real 0.5 > 0.75 no -> 0.25                        max 0.25
    #   i=1: j=2: sim 0 > 0 no, real 0 > 0.75 no -> none; others agree         max 0
    #   i=2: j=1: sim 0 > 0 no, real 0.75 > 0 yes -> 0.75; j=0, j=3 -> 0.25     max 0.75
    #   i=3: like i=0                                                          max 0.25
    # MMRV = 1.25 / 4 = 0.3125 (the paper's "<" form would charge the tie to policy 1: 0.375).
    assert mmrv([0.5, 0.0, 0.75, 0.5], [2 / 3, 0.0, 0.0, 2 / 3]) == pytest.approx(0.3125)
    # a truth tie weighs |real_i - real_j| = 0: however the simulator orders the two, no violation
    assert mmrv([0.5, 0.5], [0.1, 0.9]) == 0.0


# --- bootstrap ----------------------------------------------------------------------------------


def test_bootstrap_interval_contains_the_mean_and_is_deterministic():
    values = [0.2, 0.4, 0.6, 0.8, 1.0, 0.5, 0.7]
    mean, low, high = bootstrap_mean_ci(values, rng_seed=3)
    assert mean == pytest.approx(sum(values) / len(values))
    assert min(values) <= low < mean < high <= max(values)
    assert bootstrap_mean_ci(values, rng_seed=3) == (mean, low, high)
    assert bootstrap_mean_ci(values, rng_seed=4) != (mean, low, high)
    _, low_80, high_80 = bootstrap_mean_ci(values, rng_seed=3, level=0.8)
    assert low <= low_80 and high_80 <= high  # a lower level gives a narrower interval


def test_bootstrap_of_constant_values_is_the_point():
    assert bootstrap_mean_ci([0.1, 0.1, 0.1], rng_seed=0) == (0.1, 0.1, 0.1)
    assert bootstrap_mean_ci([0.7], rng_seed=0) == (0.7, 0.7, 0.7)


def test_bootstrap_refuses_bad_arguments():
    with pytest.raises(ValueError):
        bootstrap_mean_ci([], rng_seed=0)
    with pytest.raises(ValueError, match="level"):
        bootstrap_mean_ci([0.1, 0.2], rng_seed=0, level=1.0)
    with pytest.raises(ValueError, match="resamples"):
        bootstrap_mean_ci([0.1, 0.2], rng_seed=0, resamples=0)


# --- pairing, scores, agreement -----------------------------------------------------------------


def test_paired_episodes_pairs_by_policy_scenario_seed():
    records = [
        record("b", "s", 1, MODEL, 0.2),
        record("a", "s", 0, TRUTH, 0.9),
        record("b", "s", 1, TRUTH, 0.3),
        record("a", "s", 0, MODEL, 0.8),
    ]
    pairs = paired_episodes(records)
    assert [(t["policy"], t["backend"], m["backend"]) for t, m in pairs] == [("a", TRUTH, MODEL), ("b", TRUTH, MODEL)]
    assert [(t["pdms"], m["pdms"]) for t, m in pairs] == [(0.9, 0.8), (0.3, 0.2)]


def test_paired_episodes_refuses_a_missing_twin_naming_it():
    records = [record("a", "s", 0, TRUTH, 0.9), record("a", "s", 0, MODEL, 0.8), record("gap", "merge", 7, TRUTH, 1)]
    with pytest.raises(ValueError, match=r"'gap'.*'merge'.*seed=7.*procedural record but no world_model record"):
        paired_episodes(records)
    with pytest.raises(ValueError, match="no procedural record"):
        paired_episodes([record("a", "s", 0, MODEL, 0.8)])


def test_paired_episodes_refuses_duplicates_and_unknown_backends():
    with pytest.raises(ValueError, match="two procedural records"):
        paired_episodes([record("a", "s", 0, TRUTH, 0.9), record("a", "s", 0, TRUTH, 0.8)])
    with pytest.raises(ValueError, match="backend must be one of"):
        paired_episodes([record("a", "s", 0, "carla", 0.9)])


def test_policy_scores_are_means_with_intervals():
    records = [
        record("a", "s", 0, TRUTH, 0.8, collision=0),
        record("a", "s", 0, MODEL, 0.6, collision=1),
        record("a", "s", 1, TRUTH, 0.4, collision=1),
        record("a", "s", 1, MODEL, 0.6, collision=1),
    ]
    pdms = policy_scores(records, "pdms")["a"]
    assert pdms["truth"] == pytest.approx(0.6) and pdms["model"] == pytest.approx(0.6)
    assert pdms["model_ci"] == (0.6, 0.6)  # constant on the model side
    assert 0.4 <= pdms["truth_ci"][0] <= 0.6 <= pdms["truth_ci"][1] <= 0.8
    assert pdms["episodes"] == 2
    collision = policy_scores(records, "collision")["a"]
    assert (collision["truth"], collision["model"]) == (0.5, 1.0)
    with pytest.raises(ValueError, match="metric must be one of"):
        policy_scores(records, "comfort_score")


def test_collision_agreement_and_zoo_agreement_on_a_hand_made_set():
    # four episodes of two policies; collision flags truth [1, 0, 1, 0], model [1, 1, 0, 0]:
    # the same on episodes 1 and 4 -> 2 / 4.
    records = [
        record("p", "s", 0, TRUTH, 0.0, collision=1),
        record("p", "s", 0, MODEL, 0.0, collision=1),
        record("p", "s", 1, TRUTH, 0.9, collision=0),
        record("p", "s", 1, MODEL, 0.0, collision=1),
        record("q", "s", 0, TRUTH, 0.0, collision=1),
        record("q", "s", 0, MODEL, 0.7, collision=0),
        record("q", "s", 1, TRUTH, 0.5, collision=0),
        record("q", "s", 1, MODEL, 0.5, collision=0),
    ]
    a = agreement(records)
    assert a["collision_agreement"] == 0.5
    assert (a["episodes"], a["policies"], a["metric"]) == (4, 2, "pdms")
    # policy means: truth p 0.45, q 0.25; model p 0.0, q 0.6 -> the model reverses the two:
    # r = rho = tau = -1, MMRV = |0.45 - 0.25| = 0.2 for each, mean |delta| = (0.45 + 0.35) / 2.
    assert a["pearson"] == pytest.approx(-1.0)
    assert a["spearman"] == pytest.approx(-1.0)
    assert a["kendall"] == pytest.approx(-1.0)
    assert a["mmrv"] == pytest.approx(0.2)
    assert a["mean_abs_delta"] == pytest.approx(0.4)


def test_agreement_intervals_bracket_the_run_and_resample_whole_episodes():
    records = synthetic_records()
    a, ci = agreement(records), agreement_intervals(records, rng_seed=0, resamples=500)
    for name, (low, high) in ci.items():
        assert low <= a[name] + 1e-9 and a[name] - 1e-9 <= high, (name, low, a[name], high)
    assert ci == agreement_intervals(records, rng_seed=0, resamples=500)  # deterministic per seed
    # The same scores on every episode: nothing to resample, every draw gives the run's value.
    flat = [r | {"scenario": "s", "seed": 0} for r in records if r["scenario"] == SCENARIOS[0] and r["seed"] == 0]
    flat = [r | {"seed": seed} for r in flat for seed in (0, 1, 2)]
    for name, (low, high) in agreement_intervals(flat, resamples=200).items():
        assert (low, high) == (pytest.approx(agreement(flat)[name]),) * 2 or math.isnan(low), name
    # A policy that skipped an episode would make its means incomparable.
    with pytest.raises(ValueError, match=r"policy 'a' drove 1 of the run's 2 episodes"):
        agreement_intervals(
            [record("a", "s", 0, TRUTH, 0.5), record("a", "s", 0, MODEL, 0.5)]
            + [record(p, "s", k, b, 0.5) for p in "b" for k in (0, 1) for b in (TRUTH, MODEL)]
        )
    one = [record(p, "s", 0, b, v) for p, v in (("a", 0.2), ("b", 0.8)) for b in (TRUTH, MODEL)]
    assert all(math.isnan(low) for low, _ in agreement_intervals(one).values())  # one episode: no interval


def test_agreement_by_scenario_uses_each_scenarios_records_alone():
    records = []
    for i, (policy, truth) in enumerate([("a", 0.9), ("b", 0.5), ("c", 0.1)]):
        records += [record(policy, "easy", 0, TRUTH, truth), record(policy, "easy", 0, MODEL, truth)]
        records += [record(policy, "hard", 0, TRUTH, truth), record(policy, "hard", 0, MODEL, 0.1 * (3 - i))]
    by = agreement_by_scenario(records)
    assert list(by) == ["easy", "hard"]
    assert by["easy"]["pearson"] == pytest.approx(1.0) and by["easy"]["mmrv"] == 0.0
    assert by["hard"]["spearman"] == pytest.approx(1.0) and by["hard"]["mean_abs_delta"] > 0
    assert by["easy"]["episodes"] == by["hard"]["episodes"] == 3


def test_most_disagreeing_sorts_by_gap_then_key():
    records = []
    for policy, seed, truth, model in [("b", 0, 0.9, 0.1), ("a", 1, 0.2, 0.6), ("a", 0, 0.6, 0.2), ("c", 0, 0.5, 0.5)]:
        records += [record(policy, "s", seed, TRUTH, truth), record(policy, "s", seed, MODEL, model)]
    top = most_disagreeing(records, 3)
    assert [(p, s, seed) for p, s, seed, _, _ in top] == [("b", "s", 0), ("a", "s", 0), ("a", "s", 1)]
    assert top[0][3:] == (0.9, 0.1)
    assert len(most_disagreeing(records, 10)) == 4
    assert most_disagreeing(records, 0) == []


# --- summary, report, plot ----------------------------------------------------------------------

POLICIES = {  # name -> (family, truth PDMS level, world-model offset)
    "gap_keeper": ("modular", 0.85, -0.05),
    "lane_center": ("modular", 0.70, 0.05),
    "cnn_driver": ("learned", 0.60, -0.10),
    "jittery": ("perturbed", 0.35, 0.10),
    "late_braker": ("perturbed", 0.20, 0.02),
}
SCENARIOS = ("highway_sunny_day", "merge_cut_in")
SEEDS = (0, 1)


def synthetic_records():
    """5 policies x 2 scenarios x 2 seeds on both backends, with scores that vary by scenario and seed."""
    records = []
    for name, (family, level, offset) in POLICIES.items():
        for si, scenario in enumerate(SCENARIOS):
            for seed in SEEDS:
                wobble = 0.04 * (seed - 0.5) - 0.03 * si
                truth = min(max(level + wobble, 0.0), 1.0)
                model = min(max(level + offset - wobble, 0.0), 1.0)
                for backend, pdms in ((TRUTH, truth), (MODEL, model)):
                    crashed = int(pdms < 0.3)
                    records.append(
                        record(name, scenario, seed, backend, pdms, collision=crashed, family=family)
                        | {"off_road": int(seed == 1 and pdms < 0.4), "ttc_violation": int(pdms < 0.5)}
                    )
    return records


def members():
    return {
        name: {"family": family, "citation": f"{name}@v1", "description": f"the {name} test policy"}
        for name, (family, _, _) in POLICIES.items()
    }


def make_summary(**kw):
    header = RunHeader("world_model/checkpoints/tiny", SCENARIOS, SEEDS, steps=40, seconds=123.0)
    return build_summary(synthetic_records(), header, members=members(), **kw)


def test_build_summary_shape_and_json():
    summary = make_summary()
    assert set(summary) == {
        "checkpoint", "scenarios", "seeds", "steps", "seconds", "metrics", "bootstrap",
        "policies", "agreement", "agreement_ci", "by_scenario", "disagreements",
    }  # fmt: skip
    assert list(summary["policies"]) == sorted(POLICIES)
    entry = summary["policies"]["gap_keeper"]
    assert (entry["family"], entry["citation"], entry["episodes"]) == ("modular", "gap_keeper@v1", 4)
    for metric in summary["metrics"]:
        assert set(entry[metric]) == {"truth", "model", "truth_ci", "model_ci"}
    assert summary["agreement"]["policies"] == 5 and summary["agreement"]["episodes"] == 20
    assert list(summary["by_scenario"]) == list(SCENARIOS)
    assert len(summary["disagreements"]) == 6
    first = summary["disagreements"][0]
    assert first["key"] == episode_key(first["policy"], first["scenario"], first["seed"])
    assert first["delta"] == pytest.approx(first["model_pdms"] - first["truth_pdms"])
    assert json.loads(json.dumps(summary, allow_nan=False)) == summary  # plain JSON, no tuples or nan
    assert make_summary() == summary  # deterministic for the default seed


def test_build_summary_refuses_unlisted_runs_and_unknown_members():
    with pytest.raises(ValueError, match="does not list"):
        build_summary(synthetic_records(), RunHeader("c", SCENARIOS[:1], SEEDS, 1, 1.0), members=members())
    partial = {k: v for k, v in members().items() if k != "jittery"}
    with pytest.raises(ValueError, match="jittery"):
        build_summary(synthetic_records(), RunHeader("c", SCENARIOS, SEEDS, 1, 1.0), members=partial)


def test_markdown_report_has_the_headline_tables_and_links():
    summary = make_summary()
    worst = summary["disagreements"][0]["key"]
    summary["videos"] = {worst: f"videos/{worst.replace('/', '_')}.mp4"}
    text = markdown_report(summary)
    assert "## Agreement over the zoo" in text
    assert "| statistic | **this run** | NAVSIM v2 pseudo-simulation †" in text
    a = summary["agreement"]
    low, high = summary["agreement_ci"]["pearson"]
    assert f"| Pearson r ↑ | {a['pearson']:.3f} [{low:.3f}, {high:.3f}] | 0.89 | 0.942 | 0.924 |" in text
    low, high = summary["agreement_ci"]["mmrv"]
    assert f"| MMRV ↓ | {a['mmrv']:.3f} [{low:.3f}, {high:.3f}] | – | 0.044 | – |" in text
    assert "95% bootstrap intervals (BCa)" in text
    old = {k: v for k, v in summary.items() if k != "agreement_ci"}  # a summary written before intervals
    assert f"| Pearson r ↑ | {a['pearson']:.3f} | 0.89 |" in markdown_report(old)
    assert "| policies | 5 | 83 | – | – |" in text
    assert "Published figures of other systems" in text
    assert "not measurements of this world model" in text
    for heading in ("## Policies", "## Per scenario", "## Most disagreeing episodes"):
        assert heading in text
    # the policy table is in ground-truth PDMS order, best first
    order = [text.index(f"| `{name}` |") for name in sorted(POLICIES, key=lambda n: -POLICIES[n][1])]
    assert order == sorted(order)
    assert f"[video](videos/{worst.replace('/', '_')}.mp4)" in text
    assert "run time: 2.0 min" in text
    assert "`gap_keeper@v1` (modular): the gap_keeper test policy" in text


def test_markdown_report_shows_undefined_statistics_as_na():
    records = []
    for policy in ("a", "b"):
        for seed in SEEDS:
            records += [record(policy, "s", seed, TRUTH, 0.5), record(policy, "s", seed, MODEL, 0.4 + 0.1 * seed)]
    summary = build_summary(
        records,
        RunHeader("c", ["s"], SEEDS, steps=1, seconds=30.0),
        members={p: {"family": "learned", "citation": f"{p}@v1"} for p in ("a", "b")},
    )
    assert summary["agreement"]["pearson"] is None  # every policy's truth is 0.5: constant
    assert summary["agreement_ci"]["pearson"] is None
    text = markdown_report(summary)
    assert "| Pearson r ↑ | n/a | 0.89 |" in text


def test_scatter_plot_writes_a_readable_png(tmp_path):
    pytest.importorskip("matplotlib")
    image = pytest.importorskip("PIL.Image")
    path = scatter_plot(make_summary(), tmp_path / "plots" / "agreement.png")
    assert path == tmp_path / "plots" / "agreement.png"
    assert [p.name for p in path.parent.iterdir()] == ["agreement.png"]  # no temporary file left
    with image.open(path) as png:
        png.verify()
    with image.open(path) as png:
        assert png.format == "PNG"
        width, height = png.size
        assert 800 <= width <= 2000 and 800 <= height <= 2000
        assert len(set(png.convert("L").resize((64, 64)).getdata())) > 10  # something is drawn
