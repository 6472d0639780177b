"""The agreement run's scatter plot: world-model PDMS against ground-truth PDMS, a point per policy.

Each point has its bootstrap intervals both ways, a marker shape and colour per family, and its
policy's name placed where it overlaps least with the rest; the y = x diagonal and the zoo-level
statistics are drawn with them. It renders a summary of :func:`~m4world_env.agreement.render.build_summary`.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from m4world_env.agreement.render import level_percent, number

# Square (both axes are PDMS in [0, 1]), large enough for 24+ labelled points.
FIGURE_INCHES = (7.5, 7.5)
FIGURE_DPI = 150
LABEL_FONTSIZE = 6  # policy names: small enough that 24 labels mostly stay apart, still readable
MARKER_SIZE = 5  # points
ERROR_BAR_ALPHA = 0.45  # the bars are lighter than the markers, so a cluster's points stay visible
LABEL_HALO_WIDTH = 2.0  # a white outline keeps a name readable over the bars and the grid
# Where a name may sit relative to its point: (dx, dy) in points and the text's anchor, tried in order.
LABEL_SPOTS = (
    (4, 2, "left", "bottom"),
    (4, -2, "left", "top"),
    (-4, 2, "right", "bottom"),
    (-4, -2, "right", "top"),
    (6, 0, "left", "center"),
    (-6, 0, "right", "center"),
    (0, 5, "center", "bottom"),
    (0, -5, "center", "top"),
)
# Rings of spots, (distance scale, extra cost in squared pixels): the first touches the marker; the
# farther ones, for crowded clusters, draw a leader line, which costs some reading, so they must save
# at least that much overlap to win.
LABEL_RINGS = ((1, 0.0), (3, 20.0), (5, 40.0))
FAMILY_MARKERS = ("o", "s", "^", "D", "v", "P", "X")  # a shape per family too, for colour-blind readers
FAMILY_COLORMAP = "tab10"
# mkstemp makes its file private (0600); the plot is an ordinary report file, readable by all.
PLOT_FILE_MODE = 0o644


def _error_bars(entries: Sequence[Mapping[str, Any]], side: str) -> list[list[float]]:
    """matplotlib's asymmetric error bars, [[mean - low, ...], [high - mean, ...]], of ``side``'s
    bootstrap intervals."""
    return [[e[side] - e[f"{side}_ci"][0] for e in entries], [e[f"{side}_ci"][1] - e[side] for e in entries]]


def _overlap(a: Any, b: Any) -> float:
    """The area (squared pixels) shared by two matplotlib ``Bbox`` es."""
    width = min(a.x1, b.x1) - max(a.x0, b.x0)
    height = min(a.y1, b.y1) - max(a.y0, b.y0)
    return max(width, 0.0) * max(height, 0.0)


def _place_labels(ax: Any, points: Sequence[tuple[str, float, float]], obstacles: Sequence[Any]) -> None:
    """Name each point at the spot of :data:`LABEL_SPOTS` x :data:`LABEL_RINGS` (beyond the first ring
    with a leader line) whose text overlaps least with the markers, the names placed before it, the
    ``obstacles`` (artists: the statistics box, the legend) and the outside of the axes; greedy, from
    left to right, so the same summary always gives the same picture."""
    from matplotlib import patheffects
    from matplotlib.text import Text
    from matplotlib.transforms import Bbox

    renderer = ax.figure.canvas.get_renderer()
    radius = MARKER_SIZE * ax.figure.dpi / 72.0 / 2.0  # points -> pixels
    placed = [artist.get_window_extent(renderer) for artist in obstacles]
    for px, py in ax.transData.transform([(x, y) for _, x, y in points]):
        placed.append(Bbox.from_extents(px - radius, py - radius, px + radius, py + radius))
    frame = ax.get_window_extent(renderer)
    halo = [patheffects.withStroke(linewidth=LABEL_HALO_WIDTH, foreground="white")]
    spots = [(dx * k, dy * k, ha, va, penalty, k > 1) for k, penalty in LABEL_RINGS for dx, dy, ha, va in LABEL_SPOTS]
    # A leader line stops at the marker's edge, not over the marker.
    leader = {"arrowstyle": "-", "color": "0.5", "linewidth": 0.5, "shrinkA": 0, "shrinkB": MARKER_SIZE / 2 + 1}
    for name, x, y in sorted(points, key=lambda p: (p[1], p[2], p[0])):
        best = None
        for dx, dy, ha, va, penalty, far in spots:
            label = ax.annotate(
                name,
                (x, y),
                xytext=(dx, dy),
                textcoords="offset points",
                ha=ha,
                va=va,
                fontsize=LABEL_FONTSIZE,
                color="0.15",
                zorder=4,
                path_effects=halo,
                annotation_clip=False,
                arrowprops=leader if far else None,
            )
            # The name's own extent: an annotation's would include its leader line, which may cross
            # things; the text's alone is where the annotation put it only once its position is updated.
            label.update_positions(renderer)
            box = Text.get_window_extent(label, renderer)
            outside = box.width * box.height - _overlap(box, frame)
            cost = sum(_overlap(box, other) for other in placed) + outside + penalty
            if best is None or cost < best[0]:
                if best is not None:
                    best[1].remove()
                best = (cost, label, box)
            else:
                label.remove()
        placed.append(best[2])


def scatter_plot(summary: Mapping[str, Any], path: str | Path) -> Path:
    """A PNG of world-model PDMS (y) against ground-truth PDMS (x): one point per policy, coloured
    and shaped by family, with the bootstrap intervals as error bars, the y = x diagonal, the policy
    names, and Pearson r / Spearman rho / MMRV in a text box. Written atomically (a temporary file
    in the same folder, then ``os.replace``); returns ``path``."""
    # The object API on an Agg canvas draws without pyplot's global state or the process's backend.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    # Laid out at the saving resolution, so the labels' measured extents are the ones saved.
    fig = Figure(figsize=FIGURE_INCHES, dpi=FIGURE_DPI)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.plot([0, 1], [0, 1], linestyle="--", color="0.55", linewidth=1, label="y = x", zorder=1)

    points = _plot_families(ax, summary["policies"])

    a = summary["agreement"]
    stats_box = ax.text(
        0.03,
        0.97,
        f"Pearson r = {number(a['pearson'])}\nSpearman ρ = {number(a['spearman'])}\n"
        f"MMRV = {number(a['mmrv'])}\n{a['policies']} policies, {a['episodes']} episode pairs",
        transform=ax.transAxes,
        va="top",
        ha="left",
        fontsize=9,
        bbox={"boxstyle": "round", "facecolor": "white", "edgecolor": "0.7", "alpha": 0.9},
    )
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_aspect("equal")
    ax.grid(True, linewidth=0.4, alpha=0.5)
    ax.set_xlabel("ground-truth PDMS (procedural renderer)")
    ax.set_ylabel("world-model PDMS")
    ax.set_title(
        f"Policy PDMS: world model vs ground truth\n(error bars: {level_percent(summary)} bootstrap CI)", fontsize=11
    )
    legend = ax.legend(title="family", loc="lower right", fontsize=8, title_fontsize=8, framealpha=0.9)
    fig.tight_layout()
    # Names go last, once the layout fixes where everything is drawn.
    _place_labels(ax, points, obstacles=[stats_box, legend])

    _save_png(fig, path)
    return path


def _plot_families(ax, policies: Mapping[str, Any]) -> list[tuple[str, float, float]]:  # noqa: ANN001 - Axes
    """Each family's policies as points with their error bars, one marker and colour per family;
    the (name, x, y) of every point, for the labels."""
    from matplotlib import colormaps

    families = sorted({p["family"] for p in policies.values()})
    palette = colormaps[FAMILY_COLORMAP]
    points: list[tuple[str, float, float]] = []
    for index, family in enumerate(families):
        names = sorted(n for n, p in policies.items() if p["family"] == family)
        pdms = [policies[n]["pdms"] for n in names]
        x, y = [p["truth"] for p in pdms], [p["model"] for p in pdms]
        bars = ax.errorbar(
            x,
            y,
            xerr=_error_bars(pdms, "truth"),
            yerr=_error_bars(pdms, "model"),
            fmt=FAMILY_MARKERS[index % len(FAMILY_MARKERS)],
            color=palette(index % palette.N),
            markersize=MARKER_SIZE,
            elinewidth=0.7,
            capsize=2,
            alpha=0.85,
            label=f"{family} ({len(names)})",
            zorder=3,
        )
        # A policy scoring exactly 0 or 1 sits on the frame: keep its marker and bars whole.
        for artist in (*bars.lines[:1], *bars.lines[1], *bars.lines[2]):
            artist.set_clip_on(False)
        for artist in (*bars.lines[1], *bars.lines[2]):
            artist.set_alpha(ERROR_BAR_ALPHA)
        points += zip(names, x, y, strict=True)
    return points


def _save_png(fig, path: Path) -> None:  # noqa: ANN001 - a matplotlib Figure
    """``fig`` as a PNG at ``path``, atomically: a temporary file in the same folder, then ``os.replace``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as handle:
            fig.savefig(handle, format="png", dpi=FIGURE_DPI)
        os.chmod(tmp, PLOT_FILE_MODE)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
