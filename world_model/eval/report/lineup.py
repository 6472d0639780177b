"""Which rows a bundle's report runs, each with the id its cached scores are keyed by, and
:func:`report_bundle`, the whole report of a bundle (what ``m4world eval --report`` runs).

The lineup: the reference rows (oracle, autoencoder, road_only, first_frame), then the model rows
under ``seeds`` noise seeds each: [geometry_only], the student as the env streams it, the
student without context refresh, one row per asked refresh-step set and attention-sink size,
[student_adapted], [teacher]. A model row's id names everything its scores depend on (bundle and
weights digests, first noise seed, precision, rolling window, streaming settings), so changing
any of them regenerates that row only.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from world_model.bundle import resolve_bundle, sha256_file
from world_model.data import Clip, iter_clips
from world_model.eval.report.markdown import format_markdown
from world_model.eval.report.results import Report
from world_model.eval.report.rows import (
    RowFn,
    autoencoder_row,
    first_frame_row,
    oracle_row,
    road_only_row,
    teacher_row,
    world_model_row,
)
from world_model.eval.report.run import evaluate_rows, write_report
from world_model.precision import DTYPES
from world_model.rollout.runtime import WorldModel, load_world_model
from world_model.streaming import REFRESH_EVERY_STEP, StreamingConfig, check_changes

# How the report's flags spell the streaming settings in error messages.
REPORT_NAMES = {"refresh_steps": "--refresh-steps", "sink_frames": "--sink-frames"}


@dataclass(frozen=True)
class StudentStreaming:
    """A student row's changes to the bundle's streaming.json (:class:`StreamingConfig`'s settings,
    bounds and meanings; None keeps the bundle's): the headline row changes nothing, so it streams
    as the env does."""

    context_refresh: bool | None = None  # False: the refresh-off ablation
    refresh_steps: tuple[int, ...] | str | None = None  # refresh at these denoising steps (the refresh on)
    sink_frames: int | None = None  # keep each rollout's first N frames in context

    def __post_init__(self) -> None:
        checked = check_changes(self.changes(), REPORT_NAMES)  # in their one form: a tuple of steps or "all"
        object.__setattr__(self, "refresh_steps", checked.get("refresh_steps"))
        object.__setattr__(self, "sink_frames", checked.get("sink_frames"))

    def changes(self) -> dict[str, Any]:
        """The settings this row gives :meth:`StreamingConfig.override`."""
        changes: dict[str, Any] = {} if self.context_refresh is None else {"context_refresh": self.context_refresh}
        if self.refresh_steps is not None:
            changes |= {"context_refresh": True, "refresh_steps": self.refresh_steps}
        if self.sink_frames is not None:
            changes["sink_frames"] = self.sink_frames
        return changes

    def streaming(self, bundle: StreamingConfig) -> StreamingConfig:
        """The row's streaming: ``bundle``'s with this row's changes."""
        return bundle.override(self.changes(), REPORT_NAMES)

    @property
    def row_name(self) -> str:
        if self.context_refresh is False:
            return "student_no_refresh"
        name = "student"
        if self.refresh_steps is not None:
            steps = [self.refresh_steps] if self.refresh_steps == REFRESH_EVERY_STEP else self.refresh_steps
            name += "_refresh_" + "_".join(map(str, steps))
        if self.sink_frames is not None:
            name += f"_sink_{self.sink_frames}"
        return name

    def id_suffix(self) -> str:
        """The part of a student row's id that names its streaming settings beyond ``refresh=``."""
        if self.sink_frames is not None:
            return f",refresh_steps={self.refresh_steps},sink_frames={self.sink_frames}"
        return f",refresh_steps={self.refresh_steps}" if self.refresh_steps is not None else ""


@dataclass(frozen=True)
class ReportRequest:
    """A bundle's report: the model, the clips and the extra rows (``m4world eval --report``'s flags)."""

    checkpoint: str | None = None  # the bundle (None: the shipped one)
    evalset: str = "data/evalset"
    out: str | None = None  # folder for report.md, report.json and the row cache rows/
    seed: int = 0  # first noise seed of the model rows
    seeds: int = 3  # noise seeds per model row: seed, seed + 1, ...
    dtype: str = "auto"  # the DiTs' precision
    context_frames: int | None = None  # a rolling window other than the bundle's
    clips_prefix: str = ""
    max_clips: int = 0  # 0: all
    baseline: str | None = None  # geometry-only bundle
    teacher: str | None = None  # teacher export, RUN/teacher/model
    adapters: tuple[str, ...] = ()
    refresh_steps: tuple[tuple[int, ...], ...] = ()  # one extra student row per step set
    sink_frames: tuple[int, ...] = ()  # extra student rows per sink size (with each refresh row)

    def __post_init__(self) -> None:
        if self.seeds < 1:
            raise ValueError(f"seeds must be >= 1, got {self.seeds}")
        if self.dtype not in DTYPES:
            raise ValueError(f"dtype must be one of {DTYPES}, got {self.dtype!r}")
        self.student_streamings()  # refuses a bad step set or sink size before any model is loaded

    def student_streamings(self) -> list[StudentStreaming]:
        """Every student row's streaming settings, in the report's order."""
        out = [StudentStreaming(), StudentStreaming(context_refresh=False)]
        out += [StudentStreaming(refresh_steps=steps) for steps in self.refresh_steps]
        out += [StudentStreaming(refresh_steps=steps, sink_frames=sinks)
                for sinks in self.sink_frames for steps in (None, *self.refresh_steps)]  # fmt: skip
        return out


@dataclass(frozen=True)
class BundleReport:
    """:func:`report_bundle`'s result: the report, its markdown and the files written (None without ``out``)."""

    report: Report
    markdown: str
    written: tuple[Path, Path] | None


def report_bundle(request: ReportRequest) -> BundleReport:
    """Load the request's clips and models, score the lineup (reusing cached rows in ``out/rows``)
    and write report.md / report.json into ``out``."""
    clips = load_clips(request)
    rows, ids = bundle_rows(request)
    cache = Path(request.out) / "rows" if request.out else None
    report = evaluate_rows(rows, clips, cache_dir=cache, row_ids=ids)
    written = write_report(report, request.out) if request.out else None
    return BundleReport(report, format_markdown(report), written)


def load_clips(request: ReportRequest) -> list[Clip]:
    clips = [c for c in iter_clips(request.evalset) if c.name.startswith(request.clips_prefix)]
    clips = clips[: request.max_clips or None]
    if not clips:
        which = f"no clips named {request.clips_prefix}*" if request.clips_prefix else "no clips"
        raise ValueError(f"{which} in {request.evalset}; record them with `m4world evalset --out {request.evalset}`")
    return clips


def bundle_rows(request: ReportRequest) -> tuple[dict[str, RowFn | list[RowFn]], dict[str, str]]:
    """The lineup's rows (a model row: one generator per noise seed) and their cache ids."""

    def load(path: str | None) -> WorldModel:
        return load_world_model(path, dtype=request.dtype, context_frames=request.context_frames)

    wm = load(request.checkpoint)
    ident = RowIdentity(request, wm.dtype)

    def seeded(make_row: Callable[[int], RowFn]) -> list[RowFn]:
        return [make_row(request.seed + k) for k in range(request.seeds)]

    rows: dict[str, RowFn | list[RowFn]] = {"oracle": oracle_row}
    ids = {"oracle": "oracle"}
    rows["autoencoder"] = autoencoder_row(wm)  # the VAE's ceiling for every latent model below
    ids["autoencoder"] = ident.autoencoder()
    rows["road_only"], ids["road_only"] = road_only_row, "road_only"  # the floor of the object scores
    rows["first_frame"], ids["first_frame"] = first_frame_row, "first_frame"  # the floor of the motion scores
    if request.baseline:  # the geometry-only model (m4world train --geometry-only), streamed the same way
        baseline = load(request.baseline)
        rows["geometry_only"] = seeded(lambda s: world_model_row(baseline, seed=s))
        ids["geometry_only"] = ident.student(request.baseline)
    for row in request.student_streamings():
        streaming = row.streaming(wm.streaming)  # refuses refresh steps beyond the bundle's denoising steps
        rows[row.row_name] = seeded(lambda s, st=streaming: world_model_row(wm, seed=s, streaming=st))
        ids[row.row_name] = ident.student(request.checkpoint, row)
    if request.adapters:  # the same rollouts with LoRA adapters (§5), on a copy so the rows above stay plain
        adapted = load(request.checkpoint)
        adapted.apply_adapters(list(request.adapters))  # into the student or the reference model, as the env does
        rows["student_adapted"] = seeded(lambda s: world_model_row(adapted, seed=s))
        ids["student_adapted"] = ident.adapted(request.checkpoint, adapted)
    if request.teacher:
        from world_model.precision import dit_precision
        from world_model.train.exports import load_teacher

        with dit_precision(wm.cfg.dit.autocast_bf16):  # the teacher in the student's precision
            teacher = load_teacher(request.teacher)
        rows["teacher"] = seeded(lambda s: teacher_row(wm, teacher, seed=s))
        ids["teacher"] = ident.teacher(request.teacher)
    return rows, ids


@dataclass(frozen=True)
class RowIdentity:
    """Cache ids of a request's model rows: what each row's scores depend on, as one string."""

    request: ReportRequest
    dtype: str  # the precision the DiTs resolved to (``auto`` resolves per machine)

    def student(self, bundle: str | None, streaming: StudentStreaming = StudentStreaming()) -> str:
        r = self.request
        window = f",window={r.context_frames}" if r.context_frames else ""  # not the bundle's own
        refresh = int(streaming.context_refresh is not False)
        base = f"student,bundle={bundle_digest(bundle)},seed={r.seed},refresh={refresh}"
        return f"{base},dtype={self.dtype}{window}{streaming.id_suffix()}"

    def autoencoder(self) -> str:
        vae = sha256_file(resolve_bundle(self.request.checkpoint) / "vae.safetensors")[:16]
        return f"autoencoder,vae={vae},dtype={self.dtype}"  # cameras decode in the DiTs' dtype

    def adapted(self, bundle: str | None, wm: WorldModel) -> str:
        from world_model.lora import META, WEIGHTS

        # The JSON too: it decides how an adapter acts (a completion adapter only redraws its category).
        digests = [sha256_file(d / f)[:16] for d in wm.adapter_dirs for f in (WEIGHTS, META)]
        return f"{self.student(bundle)},adapters={'+'.join(digests)}"

    def teacher(self, export: str) -> str:
        weights = Path(export).with_suffix(".safetensors")  # RUN/teacher/model
        teacher = sha256_file(weights)[:16] if weights.exists() else export
        r = self.request
        return f"teacher={teacher},bundle={bundle_digest(r.checkpoint)},seed={r.seed},dtype={self.dtype}"


def bundle_digest(path: str | None) -> str:
    """A bundle's identity: the digest of its manifest (which lists every part's digest)."""
    return sha256_file(resolve_bundle(path) / "manifest.json")[:16]
