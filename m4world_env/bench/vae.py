"""Does the VAE keep objects? Judge scores of ground truth vs the same frames through each VAE.

The VAE is the ceiling of everything the world model renders: an object it blurs away no DiT can
draw. For each ``--vae`` (a ``vae`` stage export ``RUN/vae/model`` or a checkpoint bundle) this
reports, on frames it never trained on:

- ``ordinary_psnr_db``: camera PSNR over ``--frames`` frames spread over ``--ordinary-data``;
- ``existence``: the judge's "is it a <category>?" yes-frequency on every object box of at least
  ``--min-box-px`` pixels in those frames, autoencoded, beside ``existence_truth`` on the same
  crops of the ground truth (the Oracle). Unlike the report's crops (``eval.crops``: shorter side
  and visibility thresholds) occluded boxes count too, which lowers both scores alike;
- ``case_yes``: the same question for the long-tail category ``--case`` on the rare-object views
  of ``--case-data`` (``m4world_env.bench.longtail.rare_views``), with ``case_yes_truth``.

    m4world bench vae --vae world_model/checkpoints/default --vae runs/v2/vae/model \
        --ordinary-data data/ordinary --case-data data/rare_eval --out out/bench_vae
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from m4world_env.bench.longtail import box_crop, rare_views
from world_model.data import Clip, iter_clips
from world_model.model.reference import ReferenceConfig
from world_model.model.vae import SensorVAE, cameras_to_images, images_to_cameras

NEAR = ReferenceConfig().near_plane_m


def load_any_vae(path: str | Path) -> SensorVAE:
    """A ``vae`` stage export (``RUN/vae/model``) or the VAE of a checkpoint bundle directory."""
    p = Path(path)
    if (p / "manifest.json").exists():
        from world_model.rollout.runtime import load_world_model

        return load_world_model(p, dtype="float32").vae
    from world_model.train import load_vae

    return load_vae(p)


@torch.no_grad()
def autoencode_cameras(vae: SensorVAE, cameras: np.ndarray) -> np.ndarray:
    """uint8 (V, H, W, 3) -> the same views through the VAE, uint8. Always float32, unlike
    ``SensorVAE.reconstruct_frames`` (bf16 where the run's preset autocasts): every VAE compared alike."""
    return images_to_cameras(vae.decode(vae.encode(cameras_to_images(np.array(cameras)))))


def object_crops(clips: Sequence[Clip], frames: int, min_box_px: int) -> list[tuple[int, int, int, tuple, str]]:
    """(clip, frame, view, box, category) of every object box >= ``min_box_px`` pixels in
    ``frames`` frames spread evenly over ``clips``."""
    pairs = [(ci, f) for ci, c in enumerate(clips) for f in range(0, c.num_frames, 10)]
    idx = np.linspace(0, len(pairs) - 1, num=min(frames, len(pairs))).round().astype(int)
    out = []
    for ci, f in (pairs[i] for i in sorted(set(idx.tolist()))):
        fr = clips[ci].frames[f]
        corners = fr.object_corners_lidar()
        for o, obj in enumerate(fr.objects):
            for v in range(fr.rig.num_views):
                box = fr.rig.cameras[v].box_extent(corners[o], NEAR)
                if box is not None and (box[2] - box[0]) * (box[3] - box[1]) >= min_box_px:
                    out.append((ci, f, v, box, obj.category))
    return out


def evaluate_vae(
    vae: SensorVAE,
    judge,  # noqa: ANN001 - a JudgeBackend
    ordinary: Sequence[Clip],
    crops: Sequence[tuple],
    rare: Sequence[Clip],
    case: str,
) -> dict[str, float]:
    """The module docstring's numbers for one VAE."""
    cache: dict[tuple[int, int], np.ndarray] = {}
    se, n = 0.0, 0
    for ci, f, *_ in crops:
        if (ci, f) not in cache:
            truth = np.asarray(ordinary[ci].cameras[f])
            cache[ci, f] = autoencode_cameras(vae, truth)
            se += float(((cache[ci, f].astype(np.float64) - truth) ** 2).sum())
            n += truth.size
    recon = [box_crop(cache[ci, f][v], box) for ci, f, v, box, _ in crops]
    truth = [box_crop(np.asarray(ordinary[ci].cameras[f, v]), box) for ci, f, v, box, _ in crops]
    cats = [c[-1] for c in crops]
    views = rare_views(rare, case, 16, NEAR)
    rare_recon = [box_crop(autoencode_cameras(vae, rare[rv.clip].cameras[rv.frame])[rv.view], rv.box) for rv in views]
    rare_truth = [box_crop(np.asarray(rare[rv.clip].cameras[rv.frame, rv.view]), rv.box) for rv in views]
    return {
        "ordinary_psnr_db": 10 * float(np.log10(255.0**2 / max(se / max(n, 1), 1e-10))),
        "existence": float(np.mean(judge.is_category(recon, cats))),
        "existence_truth": float(np.mean(judge.is_category(truth, cats))),
        "object_crops": len(crops),
        "case_yes": float(np.mean(judge.is_category(rare_recon, [case] * len(views)))) if views else float("nan"),
        "case_yes_truth": float(np.mean(judge.is_category(rare_truth, [case] * len(views)))) if views else float("nan"),
        "case_views": len(views),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="m4world bench vae", description=__doc__.split("\n\n")[0])
    p.add_argument("--vae", action="append", required=True, help="VAE export or bundle (repeatable)")
    p.add_argument("--ordinary-data", required=True, help="clips without the case (not trained on)")
    p.add_argument("--case-data", required=True, help="clips with the long-tail case (not trained on)")
    p.add_argument("--case", default="tree_truck")
    p.add_argument("--frames", type=int, default=36, help="ordinary frames, spread over the clips")
    p.add_argument("--min-box-px", type=int, default=36, help="smallest object box judged (pixels)")
    p.add_argument("--out", default="out/bench_vae")
    a = p.parse_args(argv)
    from world_model.eval import load_default_judge

    torch.manual_seed(0)
    judge = load_default_judge()
    ordinary, rare = list(iter_clips(a.ordinary_data)), list(iter_clips(a.case_data))
    crops = object_crops(ordinary, a.frames, a.min_box_px)
    rows = {path: evaluate_vae(load_any_vae(path), judge, ordinary, crops, rare, a.case) for path in a.vae}
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_vae.json").write_text(json.dumps({"args": vars(a), "rows": rows}, indent=1))
    print(f"| VAE | camera PSNR (dB) | existence (truth) over {len(crops)} crops | {a.case} yes (truth) |")
    print("| --- | --- | --- | --- |")
    for path, r in rows.items():
        print(
            f"| {path} | {r['ordinary_psnr_db']:.2f} | {r['existence']:.3f} ({r['existence_truth']:.3f}) "
            f"| {r['case_yes']:.3f} ({r['case_yes_truth']:.3f}, {r['case_views']} views) |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
