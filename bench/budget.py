"""Where a mapped run loses quality: PSNR split by image region, and Acc split into the protocol's sampling floor
and the reconstruction's own error (bench/analysis/budget.py).

Reproduce:  .venv/bin/h2viz map --out /tmp/run --set mapping.runtime.threads=2   (the synthetic room; any source works)
            .venv/bin/python bench/budget.py /tmp/run [--gt-mesh FILE] [--views 20]

The run's config.yaml rebuilds its source, which is read again (the synthetic room re-renders its frames): the
training views are picked and culled exactly as `h2viz map` evaluates them, and Acc matches its metrics.json. The
"all" row pools the squared error of every view (metrics.json averages the views' PSNRs, a few tenths of a dB
higher). The Acc split needs ground truth: the synthetic room's own mesh or --gt-mesh.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.analysis.budget import RegionErrors, acc_budget, half_pixel_psnr  # noqa: E402
from bench.common import command_line, fmt, markdown_table  # noqa: E402
from h2viz.config import load_config  # noqa: E402
from h2viz.eval.metrics import observed_mask_fn  # noqa: E402
from h2viz.eval.report import load_mesh, render_view, training_views  # noqa: E402
from h2viz.mapping.checkpoint import load_checkpoint  # noqa: E402
from h2viz.mapping.mapper import Mapper  # noqa: E402
from h2viz.pipeline import EvalFrames  # noqa: E402
from h2viz.sources.base import make_source  # noqa: E402


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", type=Path, help="an `h2viz map --out` directory (config.yaml, checkpoint.pt, mesh.ply)")
    p.add_argument("--gt-mesh", type=Path, default=None, help="ground-truth mesh (default: the source's own, if any)")
    p.add_argument("--views", type=int, default=None, help="training views to render (default: eval.n_interpolate)")
    return p.parse_args(argv)


def image_budget(mapper: Mapper, frames: EvalFrames, n_views: int, downscale: int) -> tuple[RegionErrors, float]:
    """Pooled region errors over `n_views` training views spread over the run, and the views' mean half-pixel PSNR."""
    errors, shifted = RegionErrors.empty(), []
    for view in training_views(frames.frames, n_views):
        pred, _, gt_rgb, gt_depth, valid = render_view(mapper.render, view, downscale)
        errors.add(np.clip(pred, 0.0, 1.0), gt_rgb, gt_depth, valid)
        shifted.append(half_pixel_psnr(gt_rgb, valid))
    return errors, float(np.mean(shifted))


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    for name in ("config.yaml", "checkpoint.pt", "mesh.ply"):
        if not (args.run / name).is_file():
            print(f"{args.run / name} is missing: pass the --out directory of a finished `h2viz map` run")
            return 2
    cfg = load_config([args.run / "config.yaml"])
    mapper, _ = load_checkpoint(args.run / "checkpoint.pt", cfg.mapping)
    source = make_source(cfg.source)
    n_views = cfg.eval.n_interpolate if args.views is None else args.views
    frames = EvalFrames.read(source, n_views)
    if not frames.frames:
        print(f"{source.describe()}: no frames could be read")
        return 2

    errors, shifted = image_budget(mapper, frames, n_views, cfg.eval.render_downscale)
    print(f"## PSNR by region ({n_views} training views, 1/{cfg.eval.render_downscale} resolution)\n")
    header = ["region", "pixels %", "share of squared error %", "PSNR in region dB", "PSNR if region were perfect dB"]
    rows = [
        [r.region, fmt(r.pixels_pct, 1), fmt(r.error_pct, 1), fmt(r.psnr_db), fmt(r.psnr_without_db)]
        for r in errors.table()
    ]
    print(markdown_table(header, rows))
    print(f"\nthe ground truth against itself moved half a pixel: {shifted:.2f} dB (mean over the views)")

    gt = load_mesh(args.gt_mesh) if args.gt_mesh is not None else source.ground_truth_mesh()
    if gt is None:
        print("\nno ground-truth mesh (pass --gt-mesh FILE): Acc split skipped")
    else:
        mask = observed_mask_fn(frames.coarse) if cfg.eval.cull_to_observed else None
        acc = acc_budget(load_mesh(args.run / "mesh.ply"), gt, cfg.eval.n_points, mask, cfg.eval.seed)
        print(f"\n## Acc {acc.acc_cm:.3f} cm: floor {acc.floor_cm:.3f} cm ({cfg.eval.n_points} points a mesh)\n")
        header = ["distance to the true surface cm", "points %", "Acc above the floor cm"]
        rows = [[f"{b.from_cm:g}-{b.to_cm:g}", fmt(b.points_pct, 2), fmt(b.excess_cm, 4)] for b in acc.bins]
        print(markdown_table(header, rows))
        print(f"\nmean distance of the reconstruction's samples to the true surface: {acc.mean_error_cm:.3f} cm")
    print(f"\ncommand: {command_line('bench/budget.py')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
