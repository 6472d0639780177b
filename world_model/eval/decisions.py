"""What a policy reads: the sensor errors that change a driving decision.

Whole-frame scores (the LiDAR range MAE over every cell, the scene IoU over every pixel) are
dominated by the road and the sky; a policy decides from a handful of readings. Each reading
below is taken alike on a row's sensors and on the recording's (its twin), then the two compared:

* **LiDAR, nearest object per sector** (:func:`sector_range_errors`): per 30-degree azimuth sector
  and per beam band (:data:`BEAM_BANDS`), the range of the nearest return that is not the road.
  Objects are read from the recording's range map: its LiDAR casts rays against the flat road and
  the objects' boxes only (:mod:`world_model.sim.lidar`), so there its non-road returns are exactly
  what the LiDAR sees of the objects (an occluded object is in neither map). A sector whose
  recording has such a return within :data:`OBJECT_RANGE_M` holds an object; the row's nearest
  non-road return in that sector is its reading of it (none: missed). A return is the road when it
  lies less than :data:`GROUND_CLEARANCE_M` above the road plane; on the flat road this is the
  same as a return longer than ``1 - 0.3 / 1.84 = 0.84`` x its beam's flat-road range.
* **Lead vehicle in FRONT** (:func:`lead_errors`): the largest vehicle blob of a segmenter's class
  map in the view's central third; its bottom row (where it stands on the road) and centre column,
  and the range that bottom row implies on the flat road (:func:`~world_model.sensors.road_points`).
* **Lane markings at the bottom of FRONT** (:func:`lane_errors`): the lateral position, on the
  flat road, of the nearest marking left and right of the ego in the view's bottom rows.

Every function is pure: range maps (beams, azimuth) in metres, class maps (H, W) of
:data:`~world_model.eval.segmenter.SCENE_CLASSES` ids. The ``*Sums`` add up over frames, clips and
seconds; their percentiles and shares are read once pooled.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from world_model.eval.segmenter import SCENE_CLASSES
from world_model.sensors import PIXEL_CENTRE, CameraSpec, LidarSpec, road_points

# 12 sectors: "ahead", "ahead-left", "left", ... -- the resolution at which a policy tells the
# car in its lane from the one in the next lane at a few tens of metres.
SECTOR_DEG = 30.0
# The objects a policy reacts to: the BEV raster's forward reach (BevSpec.forward_m), about
# 1.3 s at highway speed.
OBJECT_RANGE_M = 40.0
# Returns lower than this above the road are the road: below every object's top (a cone is
# 0.75 m tall), above the road surface's noise in a generated range map.
GROUND_CLEARANCE_M = 0.3
# More than a car length (4.5 m) farther: the policy's gap to the object is off by a whole car.
FAR_ERROR_M = 5.0
# The close field: a car alongside in the next lane (2-3 m) or cutting in. There a policy decides
# by tenths of a metre (is the car inside the corridor it keeps clear?), so a reading more than
# CLOSE_ERROR_M off is a wrong one.
CLOSE_RANGE_M = 10.0
CLOSE_ERROR_M = 0.1
# The percentiles the report shows: the typical error and the bad tail.
P50, P95 = 50.0, 95.0

# The view a policy reads the lead vehicle and its own lane from.
FRONT_VIEW = "FRONT"
VEHICLE = SCENE_CLASSES.index("vehicle")
MARKING = SCENE_CLASSES.index("marking")
# Fewer vehicle pixels than this are segmenter speckle: a car (1.9 x 1.6 m) 40 m ahead covers
# about 12 pixels of the 64x112 FRONT view, a 2x2 blob is one about 70 m ahead.
MIN_LEAD_PIXELS = 4
# The bottom quarter of FRONT: the road about 4-7.5 m ahead at 64x112, where the ego's own lane
# lines are read before the road can bend away; long enough to hold part of a dash (3 m dash,
# 6 m gap) most of the time.
LANE_BAND_FRACTION = 0.25
# A marking seen in a single row is speckle; a painted line crosses several rows.
MIN_MARKING_ROWS = 2


def front_view_index(view_names: Sequence[str]) -> int | None:
    """The index of :data:`FRONT_VIEW` among a rig's camera names; None for a rig without one."""
    return list(view_names).index(FRONT_VIEW) if FRONT_VIEW in view_names else None


def percentile(values: Sequence[float], q: float) -> float | None:
    """The ``q``-th percentile of pooled readings (linear interpolation); None without any."""
    return float(np.percentile(values, q)) if len(values) else None


def share(count: int, of: int) -> float | None:
    """``count`` of ``of`` as a fraction; None when there is nothing to count."""
    return count / of if of else None


# ----------------------------------------------------------------------------- LiDAR sectors


@dataclass(frozen=True)
class BeamBand:
    """The beams whose elevation lies in (``bottom_deg``, ``top_deg``] degrees."""

    name: str
    top_deg: float
    bottom_deg: float

    def beams(self, spec: LidarSpec) -> np.ndarray:
        """(beams,) bool: the rows of ``spec``'s range map in the band."""
        el = np.rad2deg(spec.elevations())
        return (el <= self.top_deg) & (el > self.bottom_deg)


BEAM_BANDS = (
    BeamBand("horizon", 2.0, -2.0),  # the beams that reach a car from about 9 m out to 40 m and beyond
    BeamBand("low", -2.0, -15.0),  # the beams that meet the road 7-36 m out: near objects, low obstacles
    BeamBand("all", 90.0, -90.0),
)


def sector_count(sector_deg: float = SECTOR_DEG) -> int:
    """How many sectors of ``sector_deg`` cover the full turn (it must divide 360)."""
    n = round(360.0 / sector_deg)
    if sector_deg <= 0 or abs(n * sector_deg - 360.0) > 1e-9:
        raise ValueError(f"sector_deg must divide 360 degrees, got {sector_deg}")
    return n


def sector_centres_deg(sector_deg: float = SECTOR_DEG) -> np.ndarray:
    """(sectors,) azimuth of each sector's centre in degrees, in (-180, 180]: sector 0 is straight
    ahead, then counter-clockwise (to the left)."""
    centres = np.arange(sector_count(sector_deg)) * sector_deg
    return np.where(centres > 180.0, centres - 360.0, centres)


def sector_of_columns(spec: LidarSpec, sector_deg: float = SECTOR_DEG) -> np.ndarray:
    """(azimuth,) int: the sector of each range-map column (sector k is centred on azimuth
    ``k * sector_deg``, counter-clockwise from straight ahead; a column on an edge belongs to the
    sector counter-clockwise of it)."""
    n = sector_count(sector_deg)
    # LidarSpec.azimuths in degrees, from the column index: at 1024 columns a sector edge falls
    # exactly on a column every third sector, and only this form puts it there exactly.
    az = 180.0 - np.arange(spec.azimuth) * (360.0 / spec.azimuth)
    return np.floor((az + sector_deg / 2.0) / sector_deg).astype(np.int64) % n


def non_ground_returns(ranges: np.ndarray, spec: LidarSpec, clearance_m: float = GROUND_CLEARANCE_M) -> np.ndarray:
    """(beams, azimuth) bool: the returns of a range map (beams, azimuth) m that stand more than
    ``clearance_m`` above the flat road (``spec.mount_height`` below the LiDAR)."""
    r = np.asarray(ranges, dtype=np.float64)
    if r.shape != (spec.beams, spec.azimuth):
        raise ValueError(f"range map must be {(spec.beams, spec.azimuth)} for this LidarSpec, got {r.shape}")
    with np.errstate(invalid="ignore"):
        height = spec.mount_height + r * np.sin(spec.elevations())[:, None]
        return (r != spec.no_return) & np.isfinite(r) & (r > 0) & (height > clearance_m)


def nearest_object_range_per_sector(
    ranges: np.ndarray,
    spec: LidarSpec,
    band: BeamBand,
    sector_deg: float = SECTOR_DEG,
    clearance_m: float = GROUND_CLEARANCE_M,
) -> np.ndarray:
    """(sectors,) the range (m, as the LiDAR reports it) of the nearest non-road return
    (:func:`non_ground_returns`) in each sector (:func:`sector_of_columns`) on the ``band``'s
    beams of a range map (beams, azimuth); nan for a sector without one."""
    keep = non_ground_returns(ranges, spec, clearance_m) & band.beams(spec)[:, None]
    nearest_per_column = np.where(keep, np.asarray(ranges, dtype=np.float64), np.inf).min(axis=0)
    out = np.full(sector_count(sector_deg), np.inf)
    np.minimum.at(out, sector_of_columns(spec, sector_deg), nearest_per_column)
    out[np.isinf(out)] = np.nan
    return out


@dataclass(frozen=True)
class SectorSums:
    """One beam band's sector readings over frames: each (frame, sector) whose recording holds an
    object within range is one object; the others are empty."""

    errors_m: tuple[float, ...] = ()  # |row - recording| of every object the row also reports
    objects: int = 0
    farther: int = 0  # the row's nearest return more than FAR_ERROR_M farther than the recording's
    missed: int = 0  # no non-road return in the row's sector
    empty: int = 0
    phantom: int = 0  # empty sectors where the row reports a return within range, FAR_ERROR_M nearer
    close: int = 0  # objects within CLOSE_RANGE_M
    close_off: int = 0  # of those, missed or read more than CLOSE_ERROR_M off

    def __add__(self, other: SectorSums) -> SectorSums:
        return SectorSums(
            self.errors_m + other.errors_m,
            self.objects + other.objects,
            self.farther + other.farther,
            self.missed + other.missed,
            self.empty + other.empty,
            self.phantom + other.phantom,
            self.close + other.close,
            self.close_off + other.close_off,
        )


def sector_range_errors(
    truth: np.ndarray,
    model: np.ndarray,
    spec: LidarSpec,
    band: BeamBand,
    sector_deg: float = SECTOR_DEG,
    range_m: float = OBJECT_RANGE_M,
    far_m: float = FAR_ERROR_M,
    clearance_m: float = GROUND_CLEARANCE_M,
) -> SectorSums:
    """One frame's sector readings: the recording's range map ``truth`` and the row's ``model``,
    both (beams, azimuth) m. A sector holds an object when ``truth``'s nearest non-road return on
    the band is within ``range_m``; the row's reading of it is its own nearest one there. Objects
    within :data:`CLOSE_RANGE_M` are also held to :data:`CLOSE_ERROR_M`."""
    t = nearest_object_range_per_sector(truth, spec, band, sector_deg, clearance_m)
    m = nearest_object_range_per_sector(model, spec, band, sector_deg, clearance_m)
    with np.errstate(invalid="ignore"):
        present = t <= range_m
        seen = present & ~np.isnan(m)
        farther = seen & (m - t > far_m)
        phantom = ~present & (m <= range_m) & (np.isnan(t) | (t - m > far_m))
        close = present & (t <= CLOSE_RANGE_M)
        close_off = close & (np.isnan(m) | (np.abs(m - t) > CLOSE_ERROR_M))
    return SectorSums(
        errors_m=tuple(np.abs(m[seen] - t[seen]).tolist()),
        objects=int(present.sum()),
        farther=int(farther.sum()),
        missed=int((present & np.isnan(m)).sum()),
        empty=int((~present).sum()),
        phantom=int(phantom.sum()),
        close=int(close.sum()),
        close_off=int(close_off.sum()),
    )


# ------------------------------------------------------------------- FRONT camera, flat road


@dataclass(frozen=True)
class LeadVehicle:
    """The lead vehicle as a class map shows it: its blob's lowest row, mean column (pixel
    indices) and size."""

    bottom_row: int
    centre_col: float
    pixels: int

    def range_m(self, camera: CameraSpec, mount_height: float) -> float:
        """Horizontal distance (m) from the LiDAR to where the blob's bottom row meets the flat
        road; inf when that row is at or above the horizon."""
        x, y = road_points(camera, mount_height, self.centre_col + PIXEL_CENTRE, self.bottom_row + PIXEL_CENTRE)
        return float(np.hypot(x, y)) if np.isfinite(x) else float("inf")


def lead_vehicle(
    classes: np.ndarray, vehicle_class: int = VEHICLE, min_pixels: int = MIN_LEAD_PIXELS
) -> LeadVehicle | None:
    """The largest 8-connected blob of ``vehicle_class`` in the central third of the columns of a
    class map (H, W) (the nearer one of equal size); None without a blob of ``min_pixels``."""
    h, w = classes.shape
    lo, hi = w // 3, w - w // 3
    mask = np.zeros((h, w), dtype=bool)
    mask[:, lo:hi] = np.asarray(classes)[:, lo:hi] == vehicle_class
    labels, n = ndimage.label(mask, structure=np.ones((3, 3), dtype=bool))
    if n == 0:
        return None
    rows, cols = np.nonzero(labels)
    ids = labels[rows, cols] - 1
    sizes = np.bincount(ids, minlength=n)
    bottoms = np.full(n, -1)
    np.maximum.at(bottoms, ids, rows)
    best = max(range(n), key=lambda k: (sizes[k], bottoms[k]))  # ties: the first in scan order
    if sizes[best] < min_pixels:
        return None
    return LeadVehicle(int(bottoms[best]), float(cols[ids == best].mean()), int(sizes[best]))


@dataclass(frozen=True)
class LeadSums:
    """Lead-vehicle readings over frames: every frame whose recording shows a lead is one lead;
    those whose lead stands within OBJECT_RANGE_M on the flat road are near leads."""

    bottom_row_errors_px: tuple[float, ...] = ()  # |row - recording| where both show a lead
    centre_col_errors_px: tuple[float, ...] = ()
    range_errors_m: tuple[float, ...] = ()  # near leads whose row's lead stands on the road
    leads: int = 0
    missed: int = 0
    near_leads: int = 0
    near_farther: int = 0  # the row's lead more than FAR_ERROR_M farther, or at or above the horizon
    near_missed: int = 0
    no_lead: int = 0  # frames whose recording shows no lead
    phantom: int = 0  # of them, frames where the row shows one

    def __add__(self, other: LeadSums) -> LeadSums:
        return LeadSums(
            self.bottom_row_errors_px + other.bottom_row_errors_px,
            self.centre_col_errors_px + other.centre_col_errors_px,
            self.range_errors_m + other.range_errors_m,
            self.leads + other.leads,
            self.missed + other.missed,
            self.near_leads + other.near_leads,
            self.near_farther + other.near_farther,
            self.near_missed + other.near_missed,
            self.no_lead + other.no_lead,
            self.phantom + other.phantom,
        )


def lead_errors(
    truth: np.ndarray,
    model: np.ndarray,
    camera: CameraSpec,
    mount_height: float,
    range_m: float = OBJECT_RANGE_M,
    far_m: float = FAR_ERROR_M,
) -> LeadSums:
    """One frame's lead-vehicle readings: the class maps (H, W) of the recording's FRONT view
    (``truth``) and of the row's (``model``), ``camera`` the FRONT camera."""
    t, m = lead_vehicle(truth), lead_vehicle(model)
    if t is None:
        return LeadSums(no_lead=1, phantom=int(m is not None))
    if m is None:
        t_range = t.range_m(camera, mount_height)
        near = t_range <= range_m
        return LeadSums(leads=1, missed=1, near_leads=int(near), near_missed=int(near))
    sums = LeadSums(
        bottom_row_errors_px=(float(abs(m.bottom_row - t.bottom_row)),),
        centre_col_errors_px=(abs(m.centre_col - t.centre_col),),
        leads=1,
    )
    t_range, m_range = t.range_m(camera, mount_height), m.range_m(camera, mount_height)
    if t_range > range_m:
        return sums
    on_road = np.isfinite(m_range)
    return LeadSums(
        sums.bottom_row_errors_px,
        sums.centre_col_errors_px,
        range_errors_m=(abs(m_range - t_range),) if on_road else (),
        leads=1,
        near_leads=1,
        near_farther=int(not on_road or m_range - t_range > far_m),
    )


def lane_marking_offsets(
    classes: np.ndarray,
    camera: CameraSpec,
    mount_height: float,
    band_fraction: float = LANE_BAND_FRACTION,
    min_rows: int = MIN_MARKING_ROWS,
    marking_class: int = MARKING,
) -> np.ndarray:
    """(2,) lateral position (m, LiDAR frame y: left positive) on the flat road of the nearest lane
    marking left and right of the ego in the bottom ``band_fraction`` of a class map (H, W): per
    row the marking pixel nearest the ego on each side, their median over the rows that have one;
    nan for a side with fewer than ``min_rows`` such rows."""
    h, w = classes.shape
    first = h - max(1, round(h * band_fraction))
    rows, cols = np.nonzero(np.asarray(classes)[first:] == marking_class)
    y = road_points(camera, mount_height, cols + PIXEL_CENTRE, rows + first + PIXEL_CENTRE)[:, 1]
    out = np.full(2, np.nan)
    for side, sign in enumerate((1.0, -1.0)):  # left (y > 0), right (y < 0)
        on_side = sign * y > 0
        if not on_side.any():
            continue
        nearest = np.full(h, np.inf)
        np.minimum.at(nearest, rows[on_side], sign * y[on_side])
        found = nearest[np.isfinite(nearest)]
        if len(found) >= min_rows:
            out[side] = sign * float(np.median(found))
    return out


@dataclass(frozen=True)
class LaneSums:
    """Lane-marking readings over frames: every (frame, side) whose recording shows a marking."""

    errors_m: tuple[float, ...] = ()  # |row - recording| lateral position where both show one
    markings: int = 0
    missed: int = 0

    def __add__(self, other: LaneSums) -> LaneSums:
        return LaneSums(self.errors_m + other.errors_m, self.markings + other.markings, self.missed + other.missed)


def lane_errors(truth: np.ndarray, model: np.ndarray, camera: CameraSpec, mount_height: float) -> LaneSums:
    """One frame's lane-marking readings: class maps (H, W) of the recording's FRONT view
    (``truth``) and of the row's (``model``), ``camera`` the FRONT camera."""
    t = lane_marking_offsets(truth, camera, mount_height)
    m = lane_marking_offsets(model, camera, mount_height)
    present = ~np.isnan(t)
    seen = present & ~np.isnan(m)
    return LaneSums(
        errors_m=tuple(np.abs(m[seen] - t[seen]).tolist()),
        markings=int(present.sum()),
        missed=int((present & np.isnan(m)).sum()),
    )


# --------------------------------------------------------------------------------- together


@dataclass(frozen=True)
class DecisionSums:
    """Every reading over some frames: LiDAR sectors per beam band name (empty for a row without
    LiDAR), the lead vehicle and the lane markings (zero counts without a FRONT view)."""

    sectors: Mapping[str, SectorSums] = field(default_factory=dict)
    lead: LeadSums = LeadSums()
    lanes: LaneSums = LaneSums()

    def __add__(self, other: DecisionSums) -> DecisionSums:
        bands = dict(self.sectors)
        for name, sums in other.sectors.items():
            bands[name] = bands.get(name, SectorSums()) + sums
        return DecisionSums(bands, self.lead + other.lead, self.lanes + other.lanes)


def lidar_decisions(
    truth: np.ndarray, model: np.ndarray, spec: LidarSpec, bands: Sequence[BeamBand] = BEAM_BANDS
) -> DecisionSums:
    """One frame's sector readings on every band: range maps (beams, azimuth) m."""
    return DecisionSums({b.name: sector_range_errors(truth, model, spec, b) for b in bands})


def camera_decisions(truth: np.ndarray, model: np.ndarray, camera: CameraSpec, mount_height: float) -> DecisionSums:
    """One frame's FRONT readings: class maps (H, W) of the recording's view and the row's."""
    return DecisionSums(
        lead=lead_errors(truth, model, camera, mount_height), lanes=lane_errors(truth, model, camera, mount_height)
    )


@dataclass(frozen=True)
class ClipDecisions:
    """One clip's readings: over every frame read, and per whole second (a partial last second
    only in ``overall``)."""

    overall: DecisionSums
    per_second: tuple[DecisionSums, ...]


def pool_seconds(clips: Sequence[ClipDecisions]) -> tuple[DecisionSums, ...]:
    """Several clips' per-second readings: second k adds every clip that has a second k."""
    seconds = max((len(c.per_second) for c in clips), default=0)
    return tuple(sum((c.per_second[k] for c in clips if k < len(c.per_second)), DecisionSums()) for k in range(seconds))
