"""Long-tail case (paper §5): the rare object's appearance before/after LoRA adaptation.

Given a run with a trained VAE, a base model and a ``--stage lora`` adapter, this renders the
first frame of rare-case frames from their controls twice (same noise seed): with the base model
and with the adapter applied. ``--task completion`` (a reference model as ``--base``, §6 task c)
instead masks the rare object out of its frame, every sensor, and regenerates it under its
controls, the rest of the frame observed: the object's own rendering, apart from the scene's.
``--task reset`` renders what the env's ``reset()`` draws when a scenario names a completion
adapter: the base model's first frame from controls, then the rare object's boxes regenerated in
that generated frame with the adapter (the "base" row is the first frame alone).
It writes a PNG (rows: ground truth, the ground truth through the VAE
and back — the ceiling of any model generating through it —, base, adapted; one column per
rare-object view crop) and JSON numbers: a pluggable ``Scorer(generated_crop, truth_crop) -> float``
inside the object's projected box, median over crops. The default scorer is the L1 distance
(0-255) between the crops' mean colours. With the evaluation judge (``world_model.eval``, the
shipped CNN judge by default) it also reports the judge's existence score for the case ("is it a
<case>?" yes-frequency over the rare crops: truth, autoencoder, base, adapted) and, on ``--ordinary-data``
frames (clips without the case), the weather, time-of-day and existence yes-frequencies with and
without the adapter, to show ordinary controllability is preserved.

The whole long-tail recipe, e.g. at the tiny preset::

    m4world bench longtail record --preset tiny --out D      # D/rare (5 clips), D/base
    python -m world_model.train --stage vae     --data D/base --run R --preset tiny --steps 400
    python -m world_model.train --stage teacher --data D/base --run R --preset tiny --steps 400
    python -m world_model.train --stage lora --case tree_truck --data D/base --case-data D/rare --run R --preset tiny
    m4world bench longtail eval --run R --data D/rare --case tree_truck --ordinary-data D/base \
        --out out/longtail

``record`` runs ``m4world record``'s recorder at the preset's sensors (views and BEV): the rare
clips from scenario ``tree_truck_highway``, the base set from every scenario with
``exclude_categories``. That drops the scenarios' scripted objects only and random traffic can
still draw the rare category, so clips holding it are then left out of D/base (``filter``): the
base model never sees the case.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from world_model.data import Clip, iter_clips
from world_model.lora import apply_adapters, remove_adapters
from world_model.model.conditions import ConditionOptions, Conditions, build_condition_arrays, style_of_prompt
from world_model.model.imagedesc import VaeCropEncoder
from world_model.model.reference import ReferenceConfig, ReferenceGenerator
from world_model.model.sampler import latents_to_observations
from world_model.model.text import TextEncoder, make_text_encoder
from world_model.model.vae import SensorVAE
from world_model.raster.maps import camera_labels, lidar_nearness_maps
from world_model.train.lora_stage import load_lora_base

Scorer = Callable[[np.ndarray, np.ndarray], float]
TASKS = ("first_frame", "completion", "reset")  # how the rare views are rendered (``_render_both``)
CROP_PX = 96  # figure cell size
TEXT_PX = 14  # label band height


def mean_colour_error(generated: np.ndarray, truth: np.ndarray) -> float:
    """L1 distance (0-255 per channel, averaged) between the mean colours of two uint8 crops."""
    g = generated.reshape(-1, 3).astype(np.float64).mean(0)
    t = truth.reshape(-1, 3).astype(np.float64).mean(0)
    return float(np.abs(g - t).mean())


@dataclass(frozen=True)
class RareView:
    """One rare object seen in one camera of one frame."""

    clip: int
    frame: int
    view: int
    box: tuple[int, int, int, int]  # (x0, y0, x1, y1) end-exclusive pixels
    track: str = ""  # the object's track id (what ``--task completion`` regenerates)


def rare_views(clips: Sequence[Clip], category: str, max_views: int, near: float) -> list[RareView]:
    """Up to ``max_views`` (clip, frame, camera) crops of a ``category`` object, the largest box of
    each frame, frames spread evenly over each clip."""
    out: list[RareView] = []
    per_clip = max(1, -(-max_views // max(len(clips), 1)))
    for ci, clip in enumerate(clips):
        found = []
        for f, fr in enumerate(clip.frames):
            corners = fr.object_corners_lidar()
            best = None
            for o, obj in enumerate(fr.objects):
                if obj.category != category:
                    continue
                for v in range(fr.rig.num_views):
                    box = fr.rig.cameras[v].box_extent(corners[o], near)
                    if box is not None and (best is None or _area(box) > _area(best[1])):
                        best = (v, box, obj.track_id)
            if best is not None:
                found.append(RareView(ci, f, *best))
        idx = np.linspace(0, len(found) - 1, num=min(per_clip, len(found))).round().astype(int) if found else []
        out += [found[i] for i in sorted(set(idx))]
    return out[:max_views]


def _area(box: tuple[int, int, int, int]) -> int:
    return (box[2] - box[0]) * (box[3] - box[1])


def _condition_arrays(clips: Sequence[Clip], views: Sequence[RareView], vae: SensorVAE) -> list:
    """The controls of each view's frame (one text and image encoder for all)."""
    cfg = vae.cfg
    text, image = make_text_encoder(cfg.text), VaeCropEncoder(vae)
    arrays = []
    for rv in views:
        c = clips[rv.clip]
        fr = c.frames[rv.frame]
        bev = np.asarray(c.bev[rv.frame : rv.frame + 1])
        options = ConditionOptions(image_encoder=image, crops=c.crops, crop_since=c.crop_since, first_ego=fr.ego)
        arrays.append(build_condition_arrays([fr], bev, cfg, text, options))
    return arrays


def _conditions(clips: Sequence[Clip], views: Sequence[RareView], vae: SensorVAE) -> Conditions:
    return Conditions.collate(_condition_arrays(clips, views, vae))


def blank_object(frame, cameras: np.ndarray, track: str, margin: int, near: float) -> np.ndarray:  # noqa: ANN001
    """A copy of one frame's cameras (V, H, W, 3) with object ``track``'s projected box, grown by
    ``margin`` pixels, filled with each view's mean colour outside it: the observed latents next to
    the completed box then carry nothing of the object the VAE encoder could have smeared into them."""
    out = np.array(cameras, copy=True)
    corners = frame.object_corners_lidar()[[o.track_id for o in frame.objects].index(track)]
    for v in range(out.shape[0]):
        box = frame.rig.cameras[v].box_extent(corners, near)
        if box is None:
            continue
        h, w = out.shape[1:3]
        x0, y0, x1, y1 = (
            max(0, box[0] - margin),
            max(0, box[1] - margin),
            min(w, box[2] + margin),
            min(h, box[3] + margin),
        )
        keep = np.ones((h, w), bool)
        keep[y0:y1, x0:x1] = False
        out[v, y0:y1, x0:x1] = out[v][keep].mean(axis=0).round().astype(out.dtype) if keep.any() else 0
    return out


def box_crop(img: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
    """The pixels of ``img`` inside ``box`` (x0, y0, x1, y1)."""
    x0, y0, x1, y1 = box
    return img[y0:y1, x0:x1]


def _render(gen: ReferenceGenerator, clips, views, steps, seed, task: str, blank_px: int = -1) -> list:  # noqa: ANN001
    """One observation per view's frame: ``first_frame`` from its controls, or ``completion``: the
    frame with the view's object masked out of every sensor and regenerated (a reference model);
    ``blank_px`` >= 0 first blanks the object in the cameras (:func:`blank_object`, that margin)."""
    if task == "first_frame":
        return gen.first_frame(_conditions(clips, views, gen.vae), steps=steps, seed=seed)[1]
    out = []
    for rv, arrays in zip(views, _condition_arrays(clips, views, gen.vae), strict=True):
        if not rv.track:
            raise ValueError(f"view {rv} names no object to complete (RareView.track is empty)")
        c, f = clips[rv.clip], rv.frame
        cams = np.asarray(c.cameras[f : f + 1])
        if blank_px >= 0:
            cams = blank_object(c.frames[f], cams[0], rv.track, blank_px, gen.cfg.near_plane_m)[None]
        _, obs, _ = gen.complete_object(
            Conditions.collate([arrays]), [c.frames[f]], cams, c.lidar[f : f + 1], rv.track, steps=steps, seed=seed
        )
        out.append(obs[0][0])
    return out


@dataclass(frozen=True)
class RenderOptions:
    """How views are rendered without and with the adapters (:func:`_render_both`), as the command
    line's ``--steps``, ``--seed``, ``--task``, ``--blank-px`` and ``--case`` set it."""

    steps: int | None = None  # sampling steps; None: the preset's
    seed: int = 0  # the noise, the same for both renderings
    search_dirs: Sequence[str | Path] = ()  # where the adapters are found besides their paths
    task: str = "first_frame"  # one of TASKS
    blank_px: int = -1  # completion: the margin of the object blanked in the cameras (-1: none)
    category: str = ""  # reset: the object category the adapters complete


def _render_both(  # noqa: ANN202 (two lists of observations)
    model,  # noqa: ANN001 - MultiViewDiT
    vae: SensorVAE,
    clips: Sequence[Clip],
    views: Sequence[RareView],
    adapters: Sequence[str | Path],
    options: RenderOptions,
):
    """``views``' frames (:func:`_render`) without, then with, the adapters (same noise).

    ``reset``: what the env's ``reset()`` draws with a completion adapter of ``options.category``
    (``WorldModel.first_frame``): the base model's first frames from controls, then, with the
    adapters, that category's boxes regenerated in them (``ReferenceGenerator.complete_category``)."""
    steps, seed, search_dirs, task = options.steps, options.seed, options.search_dirs, options.task
    blank_px, category = options.blank_px, options.category
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; choose one of {TASKS}")
    gen = ReferenceGenerator(model, vae)
    if task in ("completion", "reset") and not gen.conditioned:
        raise ValueError(f"--task {task} needs a reference model as --base (RUN/reference/model)")
    if task == "reset" and not category:
        raise ValueError("task reset completes one object category: give category")
    if task == "reset":
        cond = _conditions(clips, views, vae)
        first, base_obs = gen.first_frame(cond, steps=steps, seed=seed)
        frames = [clips[rv.clip].frames[rv.frame] for rv in views]
        apply_adapters(model, adapters, search_dirs)
        try:
            completed = gen.complete_category(cond, first, frames, category, steps=steps, seed=seed)
        finally:
            remove_adapters(model)
        obs = latents_to_observations(vae, completed, vae.cfg.sensors.lidar, **cond.frames(0, 1).decoder_inputs())
        return base_obs, [o[0] for o in obs]
    base_obs = _render(gen, clips, views, steps, seed, task, blank_px)
    apply_adapters(model, adapters, search_dirs)
    try:
        adapted_obs = _render(gen, clips, views, steps, seed, task, blank_px)
    finally:
        remove_adapters(model)
    return base_obs, adapted_obs


def evaluate(
    model,  # noqa: ANN001 - MultiViewDiT
    vae: SensorVAE,
    clips: Sequence[Clip],
    views: Sequence[RareView],
    adapters: Sequence[str | Path],
    scorer: Scorer = mean_colour_error,
    options: RenderOptions = RenderOptions(),
) -> dict:
    """Render every rare view with and without ``adapters`` (same seed; ``options`` as in
    :func:`_render_both`) and score the object's box.

    Returns per-view scores, their medians and the rendered cameras (``"images"``: truth, base,
    adapted lists of (H, W, 3) uint8 views) for the figure.
    """
    if not views:
        raise ValueError("no rare-object views to evaluate: no clip shows an object of the case's category")
    base_obs, adapted_obs = _render_both(model, vae, clips, views, adapters, options)
    truth = [np.asarray(clips[rv.clip].cameras[rv.frame, rv.view]) for rv in views]
    text = make_text_encoder(vae.cfg.text) if vae.draws_labels else None
    autoencoded = [autoencode(vae, clips[rv.clip], rv.frame, text)[rv.view] for rv in views]
    base = [o.cameras[rv.view] for o, rv in zip(base_obs, views, strict=True)]
    adapted = [o.cameras[rv.view] for o, rv in zip(adapted_obs, views, strict=True)]
    rows = []
    for rv, t, e, b, a in zip(views, truth, autoencoded, base, adapted, strict=True):
        tc = box_crop(t, rv.box)
        rows.append(
            {
                "clip": clips[rv.clip].name,
                "frame": rv.frame,
                "view": rv.view,
                "box": list(rv.box),
                "autoencoder": scorer(box_crop(e, rv.box), tc),
                "base": scorer(box_crop(b, rv.box), tc),
                "adapted": scorer(box_crop(a, rv.box), tc),
            }
        )
    return {
        "scorer": getattr(scorer, "__name__", str(scorer)),
        "views": len(rows),
        "autoencoder_median": float(np.median([r["autoencoder"] for r in rows])),
        "base_median": float(np.median([r["base"] for r in rows])),
        "adapted_median": float(np.median([r["adapted"] for r in rows])),
        "per_view": rows,
        "images": {"truth": truth, "autoencoder": autoencoded, "base": base, "adapted": adapted},
    }


def autoencode(vae: SensorVAE, clip: Clip, frame: int, text: TextEncoder | None = None) -> np.ndarray:
    """Frame ``frame`` of ``clip`` through the VAE and back: cameras (V, H, W, 3), the best any
    model generating through this VAE could render (the figure's ceiling row). ``text``: the text
    encoder of a decoder that draws the scene's style."""
    cfg = vae.cfg
    labels = camera_labels(clip.frames[frame : frame + 1], cfg)
    nearness = lidar_nearness_maps(clip.frames[frame : frame + 1], cfg)
    style = style_of_prompt(clip.frames[frame].prompt, cfg, text) if vae.draws_labels else None
    cams, _ = vae.reconstruct_frames(
        clip.cameras[frame : frame + 1], clip.lidar[frame : frame + 1], labels, style, nearness
    )
    return cams[0]


def judge_rare(judge, result: dict, views: Sequence[RareView], case: str) -> dict[str, float]:  # noqa: ANN001
    """Yes-frequency of "is it a <case>?" over the rare objects' box crops, per row of the figure."""
    out = {}
    for name in result["images"]:
        crops = [box_crop(img, rv.box) for rv, img in zip(views, result["images"][name], strict=True)]
        out[name] = float(np.mean(judge.is_category(crops, [case] * len(crops))))
    return out


def ordinary_frames(clips: Sequence[Clip], count: int, near: float) -> list[RareView]:
    """``count`` frames spread over ordinary clips, each with its largest visible object's box."""
    out: list[RareView] = []
    for ci in np.linspace(0, len(clips) - 1, num=min(count, len(clips))).round().astype(int):
        clip = clips[int(ci)]
        f = clip.num_frames // 2
        fr = clip.frames[f]
        corners = fr.object_corners_lidar()
        best = None
        for o in range(len(fr.objects)):
            for v in range(fr.rig.num_views):
                box = fr.rig.cameras[v].box_extent(corners[o], near)
                if box is not None and (best is None or _area(box) > _area(best[2])):
                    best = (v, o, box)
        if best is not None:
            out.append(RareView(int(ci), f, best[0], best[2], fr.objects[best[1]].track_id))
    return out


def judge_ordinary(
    judge,  # noqa: ANN001 - a JudgeBackend
    model,  # noqa: ANN001 - MultiViewDiT
    vae: SensorVAE,
    clips: Sequence[Clip],
    frames: Sequence[RareView],
    adapters: Sequence[str | Path],
    options: RenderOptions,
) -> dict[str, dict[str, float]]:
    """Weather, time-of-day and existence (largest object) yes-frequencies on ordinary frames,
    for the truth and for the model without / with the adapters (same noise; ``options`` as in
    :func:`_render_both`). ``completion`` regenerates each frame's largest object only: its
    existence is the telling score there."""
    base_obs, adapted_obs = _render_both(model, vae, clips, frames, adapters, options)
    meta = [clips[rv.clip].frames[rv.frame] for rv in frames]
    weathers, times = [m.prompt.weather for m in meta], [m.prompt.time_of_day for m in meta]
    # Each frame's judged object is the one ordinary_frames picked (its track).
    cats = [next(o.category for o in m.objects if o.track_id == rv.track) for rv, m in zip(frames, meta, strict=True)]
    rows = {
        "truth": [np.asarray(clips[rv.clip].cameras[rv.frame]) for rv in frames],
        "base": [o.cameras for o in base_obs],
        "adapted": [o.cameras for o in adapted_obs],
    }
    out = {}
    for name, cams in rows.items():
        scene = np.stack(cams)
        crops = [box_crop(c[rv.view], rv.box) for c, rv in zip(cams, frames, strict=True)]
        out[name] = {
            "weather": float(np.mean(judge.is_weather(scene, weathers))),
            "time_of_day": float(np.mean(judge.is_time_of_day(scene, times))),
            "existence": float(np.mean(judge.is_category(crops, cats))),
        }
    return out


def figure(result: dict, views: Sequence[RareView], path: Path, margin: float = 0.5) -> None:
    """PNG grid: rows truth / autoencoder / base / adapted, one column per rare view (box crop with context)."""
    cells = []
    for name in result["images"]:
        row = []
        for rv, img in zip(views, result["images"][name], strict=True):
            x0, y0, x1, y1 = rv.box
            mx, my = round(margin * (x1 - x0)), round(margin * (y1 - y0))
            h, w = img.shape[:2]
            ctx = (max(0, x0 - mx), max(0, y0 - my), min(w, x1 + mx), min(h, y1 + my))
            crop = cv2.resize(box_crop(img, ctx), (CROP_PX, CROP_PX), interpolation=cv2.INTER_NEAREST)
            sx, sy = CROP_PX / (ctx[2] - ctx[0]), CROP_PX / (ctx[3] - ctx[1])
            p0 = (round((x0 - ctx[0]) * sx), round((y0 - ctx[1]) * sy))
            p1 = (round((x1 - ctx[0]) * sx) - 1, round((y1 - ctx[1]) * sy) - 1)
            row.append(cv2.rectangle(np.ascontiguousarray(crop), p0, p1, (255, 255, 0), 1))
        band = np.full((CROP_PX, 80, 3), 255, np.uint8)
        cv2.putText(band, name, (2, CROP_PX // 2), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
        cells.append(np.concatenate([band, *row], axis=1))
    grid = np.concatenate(cells, axis=0)
    title = np.full((TEXT_PX + 6, grid.shape[1], 3), 255, np.uint8)
    text = f"{result['scorer']} median: base {result['base_median']:.1f}  adapted {result['adapted_median']:.1f}"
    cv2.putText(title, text, (2, TEXT_PX), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(np.concatenate([title, grid], axis=0), cv2.COLOR_RGB2BGR))


def filter_dataset(src: str | Path, dst: str | Path, category: str) -> list[str]:
    """Link the clips of ``src`` without any ``category`` object into a new dataset ``dst``."""
    from world_model.data.clips import FORMAT_NAME, FORMAT_VERSION, write_json_atomic

    src, dst = Path(src).resolve(), Path(dst)
    dst.mkdir(parents=True, exist_ok=True)
    kept = []
    for clip in iter_clips(src):
        if any(o.category == category for fr in clip.frames for o in fr.objects):
            continue
        if not (dst / clip.name).exists():
            (dst / clip.name).symlink_to(src / clip.name, target_is_directory=True)
        kept.append(clip.name)
    write_json_atomic(dst / "dataset.json", {"format": FORMAT_NAME, "version": FORMAT_VERSION, "clips": kept})
    return kept


def record_case(
    out: str | Path, preset: str, case: str, scenario: str, rare_episodes: int, base_episodes: int, duration: float
) -> dict[str, int]:
    """Record ``out/rare`` (``scenario``), ``out/all`` (every scenario, scripted ``case`` objects
    dropped) and ``out/base`` (the clips of ``out/all`` without any ``case`` object)."""
    from m4world_env.recorder import RecordConfig, record
    from m4world_env.scenario import list_scenarios
    from world_model.model.config import get_preset

    s = get_preset(preset).sensors
    out = Path(out)
    common = {"height": s.height, "width": s.width, "lidar": s.lidar, "bev": s.bev, "duration": duration}
    rare = record(RecordConfig(scenarios=[scenario], episodes=rare_episodes, out=out / "rare", **common))
    everything = record(
        RecordConfig(
            scenarios=list_scenarios(), episodes=base_episodes, out=out / "all", exclude_categories=(case,), **common
        )
    )
    base = filter_dataset(out / "all", out / "base", case)
    return {"rare": len(rare), "recorded_base": len(everything), "base": len(base)}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="m4world bench longtail", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record", help="record the rare clips and a base dataset without the case")
    r.add_argument("--preset", default="tiny")
    r.add_argument("--case", default="tree_truck")
    r.add_argument("--scenario", default="tree_truck_highway")
    r.add_argument("--rare-episodes", type=int, default=5, help="rare clips (the paper: fewer than five)")
    r.add_argument("--base-episodes", type=int, default=2, help="episodes per scenario of the base set")
    r.add_argument("--duration", type=float, default=3.0, help="seconds per clip")
    r.add_argument("--out", required=True)
    f = sub.add_parser("filter", help="link the clips without the case's category into a base dataset")
    f.add_argument("--data", required=True)
    f.add_argument("--case", default="tree_truck")
    f.add_argument("--out", required=True)
    p = sub.add_parser("eval", help="render the rare object before/after adaptation: PNG + JSON numbers")
    p.add_argument("--run", required=True, help="run directory with lora/CASE/ (and vae/ unless --base is a bundle)")
    p.add_argument("--data", required=True, help="dataset with the rare-case clips (ground truth)")
    p.add_argument("--case", default="tree_truck", help="adapter name = rare object category")
    p.add_argument("--base", default=None, help="base model export or checkpoint bundle (default RUN/teacher/model)")
    p.add_argument(
        "--task",
        choices=TASKS,
        default="first_frame",
        help="first_frame: the views' frames from their controls; completion: the object masked out of its "
        "frame and regenerated (a reference model as --base); reset: as the env's reset() with a completion "
        "adapter, the base model's first frames from controls, then the case's boxes regenerated in them with "
        "the adapter; ordinary frames get first_frame and the task",
    )
    p.add_argument(
        "--blank-px",
        type=int,
        default=-1,
        help="completion: blank the object in the cameras (its box grown by this many pixels, filled with the "
        "view's mean colour) before encoding the observed frame, so no latent next to the box carries it "
        "(default -1: no blanking)",
    )
    p.add_argument("--max-views", type=int, default=8)
    p.add_argument("--steps", type=int, default=None, help="sampling steps (default: the preset's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--ordinary-data", default=None, help="clips without the case: controllability check")
    p.add_argument("--ordinary-frames", type=int, default=16)
    p.add_argument("--no-judge", action="store_true", help="skip the judge scores")
    p.add_argument("--out", default="out/longtail")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    a = parser.parse_args(argv)
    if a.cmd == "record":
        counts = record_case(a.out, a.preset, a.case, a.scenario, a.rare_episodes, a.base_episodes, a.duration)
        print(f"recorded {counts} under {a.out}")
        return 0
    if a.cmd == "filter":
        kept = filter_dataset(a.data, a.out, a.case)
        print(f"{len(kept)} clips without {a.case!r} linked into {a.out}")
        return 0
    if a.blank_px >= 0 and a.task != "completion":
        parser.error("--blank-px applies to --task completion only")
    run = Path(a.run)
    base = load_lora_base(a.base, run)
    vae, model = base.vae, base.model
    clips = list(iter_clips(a.data))
    views = rare_views(clips, a.case, a.max_views, ReferenceConfig().near_plane_m)
    dirs = [run / "lora"]
    render = RenderOptions(a.steps, a.seed, dirs, a.task, a.blank_px, category=a.case)
    result = evaluate(model, vae, clips, views, [a.case], options=render)
    out = Path(a.out)
    figure(result, views, out / "longtail.png")
    numbers = {k: v for k, v in result.items() if k != "images"}
    numbers.update(case=a.case, run=str(run), data=a.data, steps=a.steps, seed=a.seed, task=a.task, blank_px=a.blank_px)
    if not a.no_judge:
        from world_model.eval import load_default_judge

        judge = load_default_judge()
        numbers["judge_existence"] = judge_rare(judge, result, views, a.case)
        if a.ordinary_data:
            ordinary = list(iter_clips(a.ordinary_data))
            frames = ordinary_frames(ordinary, a.ordinary_frames, ReferenceConfig().near_plane_m)
            args = (judge, model, vae, ordinary, frames, [a.case])
            plain = RenderOptions(a.steps, a.seed, dirs)  # ordinary objects are never blanked
            numbers["ordinary_judge"] = judge_ordinary(*args, plain)
            if a.task != "first_frame":  # weather and time of day come from the controls there
                numbers["ordinary_judge_" + a.task] = judge_ordinary(
                    *args, replace(plain, task=a.task, category=a.case)
                )
    (out / "longtail.json").write_text(json.dumps(numbers, indent=1))
    print(
        f"{a.case}: {numbers['views']} rare-object views, {numbers['scorer']} median "
        f"base {numbers['base_median']:.2f} -> adapted {numbers['adapted_median']:.2f} "
        f"(lower is better); wrote {out / 'longtail.png'} and {out / 'longtail.json'}"
    )
    if "judge_existence" in numbers:
        print(f"judge 'is it a {a.case}?' yes-frequency: {numbers['judge_existence']}")
    for key in ("ordinary_judge", f"ordinary_judge_{a.task}"):
        if key in numbers:
            print(f"ordinary frames (weather, time of day, existence), {key}: {numbers[key]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
