"""Do teachers with and without pixel-aligned layout conditioning put road and objects where the
scene says? Scores sampled windows of held-out clips against the simulator's frames.

    m4world bench layout_ablation --data data/test \\
        --run tokens=runs/base --run layout=runs/layout --seeds 0 1 2 --out ablation.json --png ablation.png

Each ``--run NAME=DIR`` is a run directory with a ``teacher`` stage (and a ``vae`` stage; the
runs compared should share one VAE). Per run, for windows of ``--frames`` frames from each clip
and each noise seed: the teacher samples the window from the clip's controls, the VAE decodes it,
and the cameras are scored against the recording: PSNR over whole views, inside the objects'
visible pixels (the simulator's object masks) and on the visible road (the layout raster's road
cells at full resolution, objects excluded). An ``autoencoder`` row (the recording through the VAE)
bounds what a teacher can reach. ``--png`` saves, per clip, the recording, the autoencoder and
every run's first-seed sample of the first window's first frame (six views side by side).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import torch

from world_model.data import list_clips, read_clip
from world_model.data.clips import Clip
from world_model.eval.metrics import masked_psnr, psnr
from world_model.model import ConditionOptions, Conditions, build_condition_arrays, make_text_encoder
from world_model.model.imagedesc import VaeCropEncoder
from world_model.model.layout import LAYOUT_CHANNELS, layout_raster
from world_model.model.sampler import latents_to_observations, sample_latents
from world_model.model.vae import SensorVAE
from world_model.sim import ProceduralSimulator
from world_model.train.exports import EXPORT, load_teacher, load_vae

ROAD = LAYOUT_CHANNELS.index("road")


def regions(clip: Clip, frames: range, sim: ProceduralSimulator) -> tuple[np.ndarray, np.ndarray]:
    """(T, V, H, W) bool masks of the visible objects and of the visible road, cameras only."""
    objects, road = [], []
    for f in frames:
        fr = clip.frames[f]
        obj, _ = sim.object_masks(fr)
        h, w = fr.rig.resolution
        lay = layout_raster(fr, np.asarray(clip.bev[f]), fr.lidar, (h, w), 1)
        objects.append(obj)
        road.append((lay[: fr.rig.num_views, ROAD] > 0.5) & ~obj)
    return np.stack(objects), np.stack(road)


def scores(generated: np.ndarray, target: np.ndarray, objects: np.ndarray, road: np.ndarray) -> dict[str, float]:
    out = {"psnr": float(np.mean(psnr(generated, target))), "psnr_objects": np.nan, "psnr_road": np.nan}
    for key, mask in (("psnr_objects", objects), ("psnr_road", road)):
        value = masked_psnr(generated, target, mask)
        if value is not None:
            out[key] = value
    return out


def strip(cameras: np.ndarray, scale: int) -> np.ndarray:
    """(V, H, W, 3) -> one image, views side by side, upscaled."""
    row = np.concatenate(list(cameras), axis=1)
    return cv2.resize(row, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(
        prog="m4world bench layout_ablation", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--data", required=True, help="held-out clips (m4world-clips)")
    p.add_argument("--run", action="append", required=True, help="NAME=RUN_DIR (a teacher and a vae stage)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--frames", type=int, default=None, help="frames per window (default: the teacher's shortest)")
    p.add_argument("--windows", type=int, default=2, help="windows per clip, evenly spaced")
    p.add_argument("--steps", type=int, default=None, help="sampling steps (default: the teacher's sampler)")
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--png", type=Path, default=None)
    p.add_argument("--png-scale", type=int, default=4)
    args = p.parse_args(argv)

    torch.set_grad_enabled(False)
    runs = dict(item.split("=", 1) for item in args.run)
    models = {name: load_teacher(Path(d) / "teacher" / EXPORT) for name, d in runs.items()}
    vaes: dict[str, SensorVAE] = {name: load_vae(Path(d) / "vae" / EXPORT).eval() for name, d in runs.items()}
    first = next(iter(runs))
    clips = [read_clip(args.data, n) for n in list_clips(args.data)]
    sim = ProceduralSimulator()
    totals: dict[str, list[dict[str, float]]] = {"autoencoder": [], **{n: [] for n in runs}}
    pictures = []
    for clip in clips:
        cfg0 = models[first].cfg
        t = args.frames or min(cfg0.clip.train_frames)
        starts = np.linspace(0, clip.num_frames - t, args.windows).round().astype(int)
        for w, start in enumerate(starts):
            span = range(int(start), int(start) + t)
            target = np.asarray(clip.cameras[span.start : span.stop])
            objects, road = regions(clip, span, sim)
            ae, _ = vaes[first].reconstruct_frames(target, np.asarray(clip.lidar[span.start : span.stop], np.float32))
            totals["autoencoder"].append(scores(ae, target, objects, road))
            shown = [strip(target[0], args.png_scale), strip(ae[0], args.png_scale)]
            for name, model in models.items():
                cfg, vae = model.cfg, vaes[name]
                sampler = cfg.sampler if args.steps is None else replace(cfg.sampler, steps=args.steps)
                frames = clip.frames[span.start : span.stop]
                options = ConditionOptions(
                    image_encoder=VaeCropEncoder(vae), crops=clip.crops, crop_since=clip.crop_since
                )
                bev = np.asarray(clip.bev[span.start : span.stop])
                arrays = build_condition_arrays(frames, bev, cfg, make_text_encoder(cfg.text), options)
                cond = Conditions.collate([arrays])
                for seed in args.seeds:
                    gen = torch.Generator().manual_seed(seed)
                    (obs,) = latents_to_observations(
                        vae, sample_latents(model, cond, gen, sampler), **cond.decoder_inputs()
                    )
                    cams = np.stack([o.cameras for o in obs])
                    totals[name].append(scores(cams, target, objects, road))
                    if w == 0 and seed == args.seeds[0]:
                        shown.append(strip(cams[0], args.png_scale))
            if w == 0:
                pictures.append(np.concatenate(shown, axis=0))
    results = {
        name: {k: float(np.nanmean([r[k] for r in rows])) for k in rows[0]} | {"samples": len(rows)}
        for name, rows in totals.items()
    }
    for name, row in results.items():
        print(
            f"{name:>12}: " + ", ".join(f"{k}={v:.2f}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items())
        )
    if args.out:
        args.out.write_text(
            json.dumps(
                {"args": vars(args) | {"out": str(args.out), "png": str(args.png)}, "results": results}, indent=1
            )
        )
    if args.png:
        cv2.imwrite(str(args.png), np.concatenate(pictures, axis=0)[..., ::-1])
    return results


if __name__ == "__main__":
    main()
