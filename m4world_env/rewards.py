"""highway-env style reward terms as small pure functions (weights in :class:`RewardConfig`)."""

from __future__ import annotations

from m4world_env.config import RewardConfig


def lmap(value: float, src: tuple[float, float], dst: tuple[float, float]) -> float:
    """Linear map of ``value`` from range ``src`` to range ``dst``."""
    return dst[0] + (value - src[0]) * (dst[1] - dst[0]) / (src[1] - src[0])


def reward_terms(
    *,
    crashed: bool,
    speed: float,
    lane_index: int,
    num_lanes: int,
    on_road: bool,
    progress_m: float,
    max_progress_m: float,
    cfg: RewardConfig,
) -> dict[str, float]:
    """Each term in [0, 1] (collision and on_road are indicators).

    ``lane_index`` counts from the leftmost lane (highway-env's convention: the right lane has the
    highest index). ``progress_m`` is the distance driven this step; ``max_progress_m`` the distance
    driven at the road's speed limit (so a slow roundabout scores progress like a motorway).
    """
    high_speed = min(max(lmap(speed, cfg.speed_range, (0.0, 1.0)), 0.0), 1.0)
    right_lane = lane_index / max(num_lanes - 1, 1)
    progress = min(max(progress_m / max_progress_m, 0.0), 1.0) if max_progress_m > 0 else 0.0
    return {
        "collision": float(crashed),
        "high_speed": float(high_speed),
        "right_lane": float(right_lane),
        "on_road": float(on_road),
        "progress": float(progress),
    }


def combine_reward(terms: dict[str, float], cfg: RewardConfig) -> float:
    """Weighted sum; with ``cfg.normalize`` mapped to [0, 1] over the reachable range; gated by on_road."""
    weights = {k: getattr(cfg, k) for k in terms}
    reward = sum(weights[k] * v for k, v in terms.items())
    if cfg.normalize:
        worst = sum(w for w in weights.values() if w < 0)
        best = sum(w for w in weights.values() if w > 0)
        if best > worst:
            reward = lmap(reward, (worst, best), (0.0, 1.0))
    if cfg.on_road_gate:
        reward *= terms["on_road"]
    return float(reward)
