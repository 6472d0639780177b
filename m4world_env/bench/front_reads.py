"""Where a camera policy finds the lane lines and the car ahead low in FRONT, on the world model and
on the ground truth: the same pixel, or how far apart.

    m4world bench front_reads --out F.json [--scenarios highway_sunny_day ...] [--seeds 0 1 2 3] \
        [--steps 20] [--checkpoint BUNDLE]

For each scenario and seed, one episode: the built-in ``lane_keeping`` policy drives
``backend="procedural"`` (the ground truth) and its very actions are fed to ``backend="world_model"``
(cameras only), both reset with the seed, so the traffic is the same on both. After each step, both
FRONT views are read the same ways, from their pixels only:

* **Lane lines**, as the zoo's lane finder reads them (``lines_px``; ``gap_keeper``:
  ``perception.marking_peaks`` on the bottom :data:`BAND_ROWS` rows, its contrast and width): per
  row, the centre column of the innermost bright line on each side of the view's centre; a frame's
  lines are as far apart as the median over its (row, side) pairs with a line on either view of
  the two columns' difference (:data:`MISSING_PX` where one view has none), the median the lane
  finder takes of its rows. In rain and snow the lane finder also reads the streaks and flakes
  blended over both views, where they stand out from the road.
* **Lane markings**, where they are drawn (``markings_px``): the same, over the pixels the shipped
  segmenter (:mod:`world_model.eval.segmenter`, the scene IoU's) calls marking.
* **The car ahead's bottom edge**, as a learned perception sees it (``edge_px``): the nearest
  vehicle of the scene's label map in the view's central columns (the ego's path,
  :data:`PATH_FRACTION` of the width) whose bottom lies within :data:`LEAD_RANGE_M` on the road (the
  car a policy keeps its distance from; farther ones are a pixel or two above the horizon, in fog
  not drawn at all); over its bottom row's columns, the lowest row that the segmenter calls vehicle
  in at least half of them. The label map chooses the frames and the columns, never the row.

Per scenario (seeds and steps pooled): the frames read, the share of them within 1 px and within 2
px, and the median and 95th percentile of the difference in px. The ground truth's own lines,
segmented markings and edge against its label map's (``lines_truth_vs_label``,
``markings_truth_vs_label``, ``edge_truth_vs_label``) say what each reading finds
(:data:`MISSING_PX` where it finds nothing); the world model's edge against the label map
(``edge_model_vs_label``) holds both views to the scene's own edge, where the segmenter's reading
of the ground truth errs too. A bundle whose views
are not the ground truth's size is read at that size (nearest pixel). A markdown table is printed;
the JSON holds the figures and the settings.
"""

from __future__ import annotations

import sys

import numpy as np

from m4world_env.bench.lane_markings import DEFAULT_SCENARIOS, FRONT  # the same view, the same scenarios
from m4world_env.same_states import (
    model_env_kwargs,
    pooled_by_scenario,
    replay_main,
    replay_settings,
    replayed_steps,
)
from m4world_env.zoo.modular import LaneCentring
from m4world_env.zoo.perception import marking_peaks, runs
from world_model.eval.segmenter import SCENE_CLASSES, Segmenter, load_default_segmenter
from world_model.raster.classes import CLASS_PLANE, MARKING, VEHICLE
from world_model.sensors import PIXEL_CENTRE, CameraSpec, road_points
from world_model.sim.labels import LabelRasterizer

LANE_FINDER = LaneCentring()  # gap_keeper's lane finder: its band, contrast and line width
BAND_ROWS = LANE_FINDER.band_rows
PATH_FRACTION = 0.25  # the central share of the view's width the ego drives into
# The LiDAR criterion's objects' range: the car ahead a gap-keeping policy reads.
LEAD_RANGE_M = 40.0
SEGMENTED_VEHICLE = SCENE_CLASSES.index("vehicle")
SEGMENTED_MARKING = SCENE_CLASSES.index("marking")
EDGE_SHARE = 0.5  # of the car's columns the segmenter must call vehicle for a row to be its
MISSING_PX = 99.0  # a line one view has and the other has not
READINGS = (
    "lines_px",
    "lines_truth_vs_label",
    "markings_px",
    "markings_truth_vs_label",
    "edge_px",
    "edge_truth_vs_label",
    "edge_model_vs_label",
)
TOLERANCES_PX = (1, 2)


def innermost_columns(band: np.ndarray) -> np.ndarray:
    """(rows, 2) float: per row of ``band`` (rows, W) bool, the centre column of the innermost run
    left and right of the view's centre (NaN: none)."""
    centre = (band.shape[1] - 1) / 2.0
    out = np.full((band.shape[0], 2), np.nan)
    for r, row in enumerate(band):
        starts, stops = runs(row)
        mids = (starts + stops - 1) / 2.0
        left, right = mids[mids < centre], mids[mids >= centre]
        out[r] = (left.max() if len(left) else np.nan, right.min() if len(right) else np.nan)
    return out


def line_columns(image: np.ndarray) -> np.ndarray:
    """(BAND_ROWS, 2): :func:`innermost_columns` of the lines the lane finder sees in the bottom band
    of ``image`` (H, W, 3) uint8."""
    band = image[-BAND_ROWS:].astype(np.float32).mean(axis=-1)
    return innermost_columns(marking_peaks(band, LANE_FINDER.min_contrast, LANE_FINDER.max_width_px))


def marking_columns(classes: np.ndarray, marking: int) -> np.ndarray:
    """(BAND_ROWS, 2): :func:`innermost_columns` of the class ``marking`` in the bottom band of a
    class map (H, W): the segmenter's (:data:`SEGMENTED_MARKING`) or a label map's (``MARKING``)."""
    return innermost_columns(classes[-BAND_ROWS:] == marking)


def lines_apart(truth: np.ndarray, model: np.ndarray) -> float | None:
    """How far apart two :func:`innermost_columns` are: the median over the (row, side) pairs where
    either view has a line of the column difference (MISSING_PX where the other has none), as the
    lane finder takes the median of its rows; None where neither view has a line."""
    seen_t, seen_m = np.isfinite(truth), np.isfinite(model)
    either = seen_t | seen_m
    if not either.any():
        return None
    apart = np.where(seen_t & seen_m, np.abs(truth - model), MISSING_PX)
    return float(np.median(apart[either]))


def path_vehicle_columns(classes: np.ndarray) -> tuple[np.ndarray, int] | None:
    """The columns of the nearest vehicle in the view's central columns and its bottom row, from a
    label map's class ids (H, W); None where no vehicle is there."""
    w = classes.shape[1]
    half = int(round(w * PATH_FRACTION / 2))
    lo, hi = w // 2 - half, w // 2 + half
    rows, cols = np.nonzero(classes[:, lo:hi] == VEHICLE)
    if not len(rows):
        return None
    bottom = int(rows.max())
    return lo + np.unique(cols[rows == bottom]), bottom


def lead_vehicle(classes: np.ndarray, camera: CameraSpec, mount_height: float) -> tuple[np.ndarray, int] | None:
    """:func:`path_vehicle_columns` where that vehicle's bottom meets the road within
    :data:`LEAD_RANGE_M` of the LiDAR (``mount_height`` above the road); None otherwise."""
    path = path_vehicle_columns(classes)
    if path is None:
        return None
    columns, bottom = path
    u, v = np.array([columns.mean() + PIXEL_CENTRE]), np.array([bottom + PIXEL_CENTRE])
    ahead = float(road_points(camera, mount_height, u, v)[0, 0])
    return path if np.isfinite(ahead) and 0.0 < ahead <= LEAD_RANGE_M else None


def bottom_edge(segments: np.ndarray, columns: np.ndarray) -> float | None:
    """The row of the car's bottom edge in a segmenter's scene classes (H, W) over ``columns``: the
    lowest row that is vehicle in at least :data:`EDGE_SHARE` of them; None where no row is."""
    rows = np.flatnonzero((segments[:, columns] == SEGMENTED_VEHICLE).mean(axis=1) >= EDGE_SHARE)
    return float(rows.max()) if len(rows) else None


def frame_reads(
    views: np.ndarray, classes: np.ndarray, segments: np.ndarray, lead: tuple[np.ndarray, int] | None
) -> dict[str, float | None]:
    """One frame's readings of both FRONT views, ``views`` (2, H, W, 3) uint8 the ground truth's and
    the world model's, ``classes`` the scene's label map (H, W), ``segments`` (2, H, W) the
    segmenter's scene classes of the two views, ``lead`` :func:`lead_vehicle` of the scene:
    ``lines_px`` and ``markings_px`` (:func:`lines_apart` of the lane finder's lines and of the
    segmented markings), ``edge_px`` (the bottom edges' difference), and how far the ground truth's
    lines, segmented markings and edge are from its label map's (``lines_truth_vs_label``,
    ``markings_truth_vs_label``, ``edge_truth_vs_label``, the edge signed), and the world model's edge
    from the label map's (``edge_model_vs_label``, signed). None where the frame has nothing to read."""
    truth_lines, model_lines = (line_columns(v) for v in views)
    truth_marks, model_marks = (marking_columns(s, SEGMENTED_MARKING) for s in segments)
    painted = marking_columns(classes, MARKING)
    reads: dict[str, float | None] = {
        "lines_px": lines_apart(truth_lines, model_lines),
        "lines_truth_vs_label": lines_apart(painted, truth_lines),
        "markings_px": lines_apart(truth_marks, model_marks),
        "markings_truth_vs_label": lines_apart(painted, truth_marks),
        "edge_px": None,
        "edge_truth_vs_label": None,
        "edge_model_vs_label": None,
    }
    if lead is not None:
        columns, label_row = lead
        edge_t, edge_m = (bottom_edge(s, columns) for s in segments)
        reads["edge_truth_vs_label"] = MISSING_PX if edge_t is None else edge_t - label_row
        reads["edge_model_vs_label"] = MISSING_PX if edge_m is None else edge_m - label_row
        if edge_t is not None:
            reads["edge_px"] = MISSING_PX if edge_m is None else abs(edge_m - edge_t)
    return reads


def at_size(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``image`` (h, w, 3) at ``size`` (H, W), nearest pixel: a bundle whose views are not the
    ground truth's size is read at the ground truth's."""
    rows = np.arange(size[0]) * image.shape[0] // size[0]
    cols = np.arange(size[1]) * image.shape[1] // size[1]
    return image[rows][:, cols]


def episode(scenario: str, seed: int, steps: int, model: dict, segmenter: Segmenter) -> list[dict[str, float | None]]:
    """Up to ``steps`` policy steps of ``scenario``: each frame's :func:`frame_reads`."""
    rasterizer = LabelRasterizer()
    out = []
    for step in replayed_steps(scenario, seed, steps, model):
        truth = step.truth_obs["cameras"][FRONT]
        model_view = at_size(step.model_obs["cameras"][FRONT], truth.shape[:2])
        frame = step.truth.scene_frame
        classes = rasterizer.maps(frame, frame.rig, *truth.shape[:2])[FRONT, CLASS_PLANE]
        lead = lead_vehicle(classes, frame.rig.cameras[FRONT], step.truth.lidar_spec.mount_height)
        views = np.stack([truth, model_view])
        out.append(frame_reads(views, classes, segmenter.predict(views), lead))
    return out


def summary(values: list[float]) -> dict[str, float | int | None]:
    """Frames read, the share within each of :data:`TOLERANCES_PX`, the median and 95th percentile."""
    if not values:
        return {"frames": 0, **{f"within_{k}px": None for k in TOLERANCES_PX}, "median_px": None, "p95_px": None}
    a = np.asarray(values, dtype=np.float64)
    return {
        "frames": len(a),
        **{f"within_{k}px": float((a <= k).mean()) for k in TOLERANCES_PX},
        "median_px": float(np.median(a)),
        "p95_px": float(np.percentile(a, 95)),
    }


def figures(reads: list[dict[str, float | None]]) -> dict[str, dict]:
    """:func:`summary` of each reading over a scenario's frames (those that have it)."""
    return {key: summary([abs(r[key]) for r in reads if r[key] is not None]) for key in READINGS}


def _cells(f: dict) -> list[str]:
    """A :func:`summary`'s cells of :func:`table`'s row."""
    if not f["frames"]:
        return ["0", "-", "-", "-", "-"]
    shares = [f"{f[f'within_{k}px']:.2f}" for k in TOLERANCES_PX]
    return [str(f["frames"]), *shares, f"{f['median_px']:.1f}", f"{f['p95_px']:.1f}"]


def table(results: dict[str, dict]) -> str:
    """A markdown table: per scenario and reading, frames, the shares within each tolerance, median and p95."""
    head = ["scenario", "reading", "frames", *(f"within {k} px" for k in TOLERANCES_PX), "median px", "p95 px"]
    rows = [[name, key, *_cells(f)] for name, per in results.items() for key, f in per.items()]
    return "\n".join("| " + " | ".join(row) + " |" for row in [head, ["---"] * len(head), *rows])


def run(scenarios: list[str], seeds: list[int], steps: int, checkpoint: str | None) -> dict:
    """Every episode; the figures per scenario (seeds pooled), with the settings."""
    model = model_env_kwargs(("cameras",), checkpoint)  # the cameras alone: no LiDAR decoded
    segmenter = load_default_segmenter()
    pooled = pooled_by_scenario(scenarios, seeds, lambda scenario, s: episode(scenario, s, steps, model, segmenter))
    results = {scenario: figures(reads) for scenario, reads in pooled.items()}
    settings = {"path_fraction": PATH_FRACTION, "lead_range_m": LEAD_RANGE_M, "edge_share": EDGE_SHARE}
    return {**replay_settings(scenarios, seeds, steps, checkpoint), **settings, "results": results}


def main(argv: list[str] | None = None) -> int:
    return replay_main("m4world bench front_reads", __doc__, (DEFAULT_SCENARIOS, (0, 1, 2, 3), 20), run, table, argv)


if __name__ == "__main__":
    sys.exit(main())
