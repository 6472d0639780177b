"""Statistics of agreement between the world-model backend and the ground truth over a policy zoo.

Every policy of the zoo drives the same (scenario, seed) episodes on both backends; each episode
gives one record ``{"policy", "family", "scenario", "seed", "backend", "pdms", "collision",
"off_road", "progress", "ttc_violation", ...}`` with ``backend`` one of :data:`TRUTH`
(``"procedural"``) and :data:`MODEL` (``"world_model"``). A learned simulator is judged the way the
field judges one: by how well the policies' mean scores under it agree with their scores under the
ground truth (NAVSIM's pseudo-simulation Pearson r over planners, SIMPLER's and WorldEval's Pearson r
and MMRV over robot policies), i.e. whether it ranks and scores the policies as the truth does.

A statistic that is undefined for its input (a correlation with a constant side) is ``nan``; the
functions never return numpy scalars.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
from scipy import stats as scipy_stats

TRUTH = "procedural"
MODEL = "world_model"
BACKENDS = (TRUTH, MODEL)
METRICS = ("pdms", "collision", "off_road", "progress", "ttc_violation")
DEFAULT_RESAMPLES = 2000
DEFAULT_LEVEL = 0.95

Record = Mapping[str, Any]
EpisodeKey = tuple[str, str, int]  # (policy, scenario, seed)


def episode_key(policy: str, scenario: str, seed: int) -> str:
    """The text name of an episode, ``"policy/scenario/seed"`` (the key of a summary's videos)."""
    return f"{policy}/{scenario}/{int(seed)}"


def _pair_arrays(x: Sequence[float], y: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """``x`` and ``y`` as float arrays of one equal, non-zero length with finite values."""
    a, b = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if a.ndim != 1 or b.ndim != 1 or a.shape != b.shape:
        raise ValueError(f"need two 1-D sequences of equal length, got shapes {a.shape} and {b.shape}")
    if a.size == 0:
        raise ValueError("need at least one pair of values, got none")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise ValueError("values must be finite (a nan or inf score is a broken episode, not a score)")
    return a, b


# Row-wise forms: (B, P) scores -> (B,) statistics, one per row; the functions below are their one-row
# case, and the bootstrap evaluates all its draws at once with them.


def _pearson_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pearson's r of each row pair; nan where either row has no spread (0/0: one value included)."""
    da, db = a - a.mean(axis=-1, keepdims=True), b - b.mean(axis=-1, keepdims=True)
    constant = (np.ptp(a, axis=-1) == 0) | (np.ptp(b, axis=-1) == 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = (da * db).sum(axis=-1) / np.sqrt((da * da).sum(axis=-1) * (db * db).sum(axis=-1))
    return np.where(constant, np.nan, np.clip(r, -1.0, 1.0))


def _spearman_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return _pearson_rows(scipy_stats.rankdata(a, axis=-1), scipy_stats.rankdata(b, axis=-1))


def _kendall_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """tau-b = sum_{i<j} s_a s_b / sqrt(sum_{i<j} s_a^2 * sum_{i<j} s_b^2), s = sign of the pair's
    difference (every pair counted twice on both sides of the ratio: the same ratio)."""
    sa = np.sign(a[..., :, None] - a[..., None, :])
    sb = np.sign(b[..., :, None] - b[..., None, :])
    constant = (np.ptp(a, axis=-1) == 0) | (np.ptp(b, axis=-1) == 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        tau = (sa * sb).sum(axis=(-2, -1)) / np.sqrt((sa * sa).sum(axis=(-2, -1)) * (sb * sb).sum(axis=(-2, -1)))
    return np.where(constant, np.nan, tau)


def _mmrv_rows(real: np.ndarray, sim: np.ndarray) -> np.ndarray:
    # violated[..., i, j]: the simulator's strict order of (i, j) differs from the truth's
    violated = (sim[..., :, None] > sim[..., None, :]) != (real[..., :, None] > real[..., None, :])
    weights = np.abs(real[..., :, None] - real[..., None, :]) * violated
    return weights.max(axis=-1).mean(axis=-1)


def pearson(x: Sequence[float], y: Sequence[float]) -> float:
    """Pearson's linear correlation

        r = sum_i (x_i - mean x)(y_i - mean y) / sqrt(sum_i (x_i - mean x)^2 * sum_i (y_i - mean y)^2)

    in [-1, 1]; ``nan`` when either side is constant (zero variance, including a single value):
    the ratio is 0/0 there, and no value would be honest (SIMPLER's code returns 1 when both sides
    are the same constant; here a zoo whose scores do not vary has no correlation to report)."""
    a, b = _pair_arrays(x, y)
    return float(_pearson_rows(a, b))


def spearman(x: Sequence[float], y: Sequence[float]) -> float:
    """Spearman's rank correlation: Pearson's r of the ranks,

        rho = pearson(rank(x), rank(y)),

    with tied values given the average of the ranks they span (ranks of [0.2, 0.5, 0.5, 0.9] are
    [1, 2.5, 2.5, 4]). ``nan`` when either side is constant (its ranks are constant too)."""
    a, b = _pair_arrays(x, y)
    return float(_spearman_rows(a, b))


def kendall_tau(x: Sequence[float], y: Sequence[float]) -> float:
    """Kendall's tau-b, which corrects for ties:

        tau_b = (n_c - n_d) / sqrt((n_0 - n_x) * (n_0 - n_y))

    over the n_0 = n (n - 1) / 2 pairs: n_c concordant, n_d discordant, n_x pairs tied in x and n_y
    pairs tied in y (a pair tied on one side is neither concordant nor discordant). ``nan`` when
    either side is constant (every pair is tied there: the denominator is 0)."""
    a, b = _pair_arrays(x, y)
    return float(_kendall_rows(a, b))


def mmrv(real: Sequence[float], sim: Sequence[float]) -> float:
    """SIMPLER's Mean Maximum Rank Violation (Li et al. 2024, "Evaluating Real-World Robot
    Manipulation Policies in Simulation"), in the scores' own unit, lower is better:

        RankViolation(i, j) = |real_i - real_j| * 1[(sim_i > sim_j) != (real_i > real_j)]
        MMRV = (1 / N) * sum_i max_j RankViolation(i, j)

    Each policy i is charged its worst mis-ordering, weighted by how far apart the truth puts the
    two policies, so swapping two near-equal policies costs little and swapping the best and the
    worst costs their whole gap.

    Ties follow SIMPLER's reference code (``simpler_env/utils/metrics.py``,
    ``mean_maximum_rank_violation``), which compares with a strict ``>``:

    * tied in ``real``: the weight |real_i - real_j| is 0, so no violation;
    * tied in ``sim`` but not in ``real``: the simulator failed to separate them; the pair is a
      violation charged to the policy the truth ranks higher (for it, ``sim_i > sim_j`` is false
      while ``real_i > real_j`` is true), not to the lower one.

    The paper writes the indicator with ``<``, which charges a ``sim`` tie to the lower policy
    instead; the two agree whenever ``sim`` has no ties, and the published SIMPLER figures come
    from the code. A single policy has nothing to violate: 0."""
    r, s = _pair_arrays(real, sim)
    return float(_mmrv_rows(r, s))


def bootstrap_mean_ci(
    values: Sequence[float],
    *,
    rng_seed: int,
    resamples: int = DEFAULT_RESAMPLES,
    level: float = DEFAULT_LEVEL,
) -> tuple[float, float, float]:
    """(mean, low, high): the sample mean and its percentile-bootstrap interval at ``level``.

    ``resamples`` times, draw n values with replacement and take their mean m_b; the interval is
    the (1 - level) / 2 and (1 + level) / 2 quantiles of {m_b}. The draws come from
    ``numpy.random.default_rng(rng_seed)``: the same values and seed give the same interval. A
    constant sample (one value included) has no spread to resample: (c, c, c) exactly."""
    x = np.asarray(values, dtype=np.float64)
    if x.ndim != 1 or x.size == 0:
        raise ValueError(f"need a non-empty 1-D sequence of values, got shape {x.shape}")
    if not np.isfinite(x).all():
        raise ValueError("values must be finite")
    if resamples < 1:
        raise ValueError(f"resamples must be >= 1, got {resamples}")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    mean = float(x.mean())
    if np.ptp(x) == 0:
        # The resampled means would equal c only up to rounding; the interval of a constant is c.
        c = float(x[0])
        return c, c, c
    rng = np.random.default_rng(rng_seed)
    means = x[rng.integers(0, x.size, size=(resamples, x.size))].mean(axis=1)
    low, high = np.quantile(means, [(1.0 - level) / 2.0, (1.0 + level) / 2.0])
    return mean, float(low), float(high)


def _key(record: Record) -> EpisodeKey:
    return str(record["policy"]), str(record["scenario"]), int(record["seed"])


def _describe(key: EpisodeKey) -> str:
    policy, scenario, seed = key
    return f"policy={policy!r} scenario={scenario!r} seed={seed}"


def paired_episodes(records: Iterable[Record]) -> list[tuple[Record, Record]]:
    """(truth record, model record) for every (policy, scenario, seed), sorted by that key.

    Raises ``ValueError`` naming the episode when one has a record on one backend only (a score
    without its twin would bias the policy's mean on one side), when one backend has two records of
    the same episode, or when a record names another backend."""
    by_backend: dict[str, dict[EpisodeKey, Record]] = {b: {} for b in BACKENDS}
    for record in records:
        backend = record["backend"]
        if backend not in by_backend:
            raise ValueError(f"episode {_describe(_key(record))}: backend must be one of {BACKENDS}, got {backend!r}")
        key = _key(record)
        if key in by_backend[backend]:
            raise ValueError(f"episode {_describe(key)} has two {backend} records")
        by_backend[backend][key] = record
    truth, model = by_backend[TRUTH], by_backend[MODEL]
    for key in sorted(truth.keys() ^ model.keys()):
        has, lacks = (TRUTH, MODEL) if key in truth else (MODEL, TRUTH)
        raise ValueError(f"episode {_describe(key)} has a {has} record but no {lacks} record")
    return [(truth[key], model[key]) for key in sorted(truth)]


def _check_metric(metric: str) -> None:
    if metric not in METRICS:
        raise ValueError(f"metric must be one of {METRICS}, got {metric!r}")


def _by_policy(pairs: Sequence[tuple[Record, Record]]) -> dict[str, list[tuple[Record, Record]]]:
    """The pairs of each policy in (scenario, seed) order, policies in name order."""
    grouped: dict[str, list[tuple[Record, Record]]] = {}
    for truth, model in pairs:  # paired_episodes sorts by (policy, scenario, seed)
        grouped.setdefault(str(truth["policy"]), []).append((truth, model))
    return grouped


def policy_scores(
    records: Iterable[Record],
    metric: str,
    *,
    rng_seed: int = 0,
    resamples: int = DEFAULT_RESAMPLES,
    level: float = DEFAULT_LEVEL,
) -> dict[str, dict[str, Any]]:
    """policy -> {"truth": mean, "model": mean, "truth_ci": (low, high), "model_ci": (low, high),
    "episodes": n} of ``metric`` over the policy's paired episodes (a 0/1 flag's mean is its rate).

    Intervals are :func:`bootstrap_mean_ci` over the policy's episodes in (scenario, seed) order.
    Every policy and both backends use the same ``rng_seed``: an interval describes one policy on
    one backend alone, and a shared seed keeps it the same whichever other policies run."""
    _check_metric(metric)
    scores: dict[str, dict[str, Any]] = {}
    for policy, pairs in _by_policy(paired_episodes(records)).items():
        t, t_low, t_high = bootstrap_mean_ci(
            [float(truth[metric]) for truth, _ in pairs], rng_seed=rng_seed, resamples=resamples, level=level
        )
        m, m_low, m_high = bootstrap_mean_ci(
            [float(model[metric]) for _, model in pairs], rng_seed=rng_seed, resamples=resamples, level=level
        )
        scores[policy] = {
            "truth": t,
            "model": m,
            "truth_ci": (t_low, t_high),
            "model_ci": (m_low, m_high),
            "episodes": len(pairs),
        }
    return scores


def agreement(records: Iterable[Record], metric: str = "pdms") -> dict[str, Any]:
    """How well the world model's policy scores agree with the ground truth's.

    Over the policies' mean ``metric`` (truth t_p, model m_p, P policies):

    * ``pearson``, ``spearman``, ``kendall``: correlations of (t_p) and (m_p) (``nan`` when either
      side is constant, e.g. a single policy);
    * ``mmrv``: :func:`mmrv` with real = t, sim = m;
    * ``mean_abs_delta``: (1 / P) * sum_p |m_p - t_p|.

    Over the E paired episodes: ``collision_agreement`` = (1 / E) * sum_e 1[collision flag of e is
    the same on both backends]. Plus ``metric``, ``episodes`` (E) and ``policies`` (P)."""
    _check_metric(metric)
    pairs = paired_episodes(records)
    if not pairs:
        raise ValueError("no episodes to compare")
    grouped = _by_policy(pairs)
    truth = [float(np.mean([float(t[metric]) for t, _ in ps])) for ps in grouped.values()]
    model = [float(np.mean([float(m[metric]) for _, m in ps])) for ps in grouped.values()]
    same_collision = [bool(t["collision"]) == bool(m["collision"]) for t, m in pairs]
    return {
        "metric": metric,
        "pearson": pearson(truth, model),
        "spearman": spearman(truth, model),
        "kendall": kendall_tau(truth, model),
        "mmrv": mmrv(truth, model),
        "mean_abs_delta": float(np.mean(np.abs(np.subtract(model, truth)))),
        "collision_agreement": float(np.mean(same_collision)),
        "episodes": len(pairs),
        "policies": len(grouped),
    }


# The statistics of :func:`agreement` that :func:`agreement_intervals` bounds.
INTERVAL_STATISTICS = ("pearson", "spearman", "kendall", "mmrv", "mean_abs_delta", "collision_agreement")


def agreement_intervals(
    records: Iterable[Record],
    metric: str = "pdms",
    *,
    rng_seed: int = 0,
    resamples: int = DEFAULT_RESAMPLES,
    level: float = DEFAULT_LEVEL,
) -> dict[str, tuple[float, float]]:
    """statistic -> (low, high): bootstrap intervals at ``level`` of :func:`agreement`'s statistics
    (:data:`INTERVAL_STATISTICS`), the run's episodes resampled.

    The unit drawn is the episode, a (scenario, seed) pair that every policy drove: each of
    ``resamples`` draws takes the E episodes with replacement and recomputes every policy's means on
    both backends from them, then the statistics, so a scene that is hard for the world model weighs
    on every policy of a draw at once, as it does in the run. The intervals are bias-corrected and
    accelerated (BCa, ``scipy.stats.bootstrap``): a correlation of noisy means is biased low under
    resampling, and the percentile interval of its draws would lie mostly below the run's own value.
    ``(nan, nan)`` where the bootstrap cannot tell (fewer than two episodes, a constant side).
    Every policy must have driven every episode (an agreement run's plan), else ``ValueError``."""
    _check_metric(metric)
    if resamples < 1:
        raise ValueError(f"resamples must be >= 1, got {resamples}")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    grouped = _by_policy(paired_episodes(records))
    if not grouped:
        raise ValueError("no episodes to compare")
    episodes = {(str(t["scenario"]), int(t["seed"])) for ps in grouped.values() for t, _ in ps}
    for policy, ps in grouped.items():
        if len(ps) != len(episodes):
            raise ValueError(f"policy {policy!r} drove {len(ps)} of the run's {len(episodes)} episodes")
    undefined = {name: (math.nan, math.nan) for name in INTERVAL_STATISTICS}
    if len(episodes) < 2:
        return undefined
    # (P, E) in one episode order for all: _by_policy keeps each policy's pairs in (scenario, seed) order.
    truth = np.array([[float(t[metric]) for t, _ in ps] for ps in grouped.values()])
    model = np.array([[float(m[metric]) for _, m in ps] for ps in grouped.values()])
    same = np.array([[bool(t["collision"]) == bool(m["collision"]) for t, m in ps] for ps in grouped.values()])

    def statistics(drawn: np.ndarray, axis: int = -1) -> np.ndarray:
        """(..., E) drawn episode indices -> (6, ...) statistics, one per draw."""
        t = np.moveaxis(truth[:, drawn].mean(axis=-1), 0, -1)  # (..., P)
        m = np.moveaxis(model[:, drawn].mean(axis=-1), 0, -1)
        return np.stack(
            [
                _pearson_rows(t, m),
                _spearman_rows(t, m),
                _kendall_rows(t, m),
                _mmrv_rows(t, m),
                np.abs(m - t).mean(axis=-1),
                same[:, drawn].mean(axis=(0, -1)),
            ]
        )

    run = statistics(np.arange(len(episodes)))
    if np.isnan(run).any():
        return undefined
    with warnings.catch_warnings():
        # A statistic whose jackknife values are all equal has no acceleration (0/0): nan, below.
        warnings.simplefilter("ignore", scipy_stats.DegenerateDataWarning)
        warnings.simplefilter("ignore", RuntimeWarning)
        result = scipy_stats.bootstrap(
            (np.arange(len(episodes)),),
            statistics,
            vectorized=True,
            n_resamples=resamples,
            confidence_level=level,
            method="BCa",
            random_state=np.random.default_rng(rng_seed),
        )
    out = {}
    for k, name in enumerate(INTERVAL_STATISTICS):
        low, high = float(result.confidence_interval.low[k]), float(result.confidence_interval.high[k])
        if math.isnan(low) and np.ptp(result.bootstrap_distribution[k]) == 0:
            low = high = float(run[k])  # every draw gives the run's value: nothing to bound
        out[name] = (low, high)
    return out


def agreement_by_scenario(records: Iterable[Record], metric: str = "pdms") -> dict[str, dict[str, Any]]:
    """scenario -> :func:`agreement` over that scenario's records alone, scenarios in name order."""
    by_scenario: dict[str, list[Record]] = {}
    for record in records:
        by_scenario.setdefault(str(record["scenario"]), []).append(record)
    return {name: agreement(by_scenario[name], metric) for name in sorted(by_scenario)}


def most_disagreeing(records: Iterable[Record], k: int) -> list[tuple[str, str, int, float, float]]:
    """The ``k`` episodes with the largest |model PDMS - truth PDMS|, as (policy, scenario, seed,
    truth_pdms, model_pdms), largest first; equal gaps in (policy, scenario, seed) order."""
    if k < 0:
        raise ValueError(f"k must be >= 0, got {k}")
    rows = [(*_key(t), float(t["pdms"]), float(m["pdms"])) for t, m in paired_episodes(records)]
    rows.sort(key=lambda row: (-abs(row[4] - row[3]), row[0], row[1], row[2]))
    return rows[:k]
