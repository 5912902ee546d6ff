"""The PSNR ceiling of the map's colour representation (bench/analysis/ceiling.py): the colour hash grid and decoder
that `h2viz map` trains, fitted straight to the ground-truth colours of the views that are scored, at their
true surface points, with a squared loss: in practice an upper bound for mapping runs with that representation
on those views; the curve over the steps shows whether the fit has levelled off.

Reproduce:  .venv/bin/python bench/ceiling.py [--datasets synthetic,fountain,redkitchen] [--steps 3000]
                [--batch 65536] [--loss l2|l1] [--render surface|volume]
                [--variant mapping.representation.hash_levels=5,mapping.representation.hash_log2_size=21 ...]
                [--set key=value ...]

--run DIR takes a finished `h2viz map --out DIR` run instead of --datasets: its source and settings, and a first
row with the run's own colour field scored at the same points, so that what mapping learned and what the
representation can hold are compared on equal terms (both at exact geometry).

Each --variant is one more colour representation to fit (comma-separated overrides on top of --set); the
paper's defaults always come first. Views are picked and shrunk as `h2viz map` scores them (eval.n_interpolate
training views at 1/eval.render_downscale).
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.analysis.ceiling import (  # noqa: E402
    LOSSES,
    RENDERS,
    CeilingPoint,
    SurfaceColours,
    fit_colour_ceiling,
    predict,
    score,
    surface_colours,
)
from bench.common import DATASETS, MissingData, command_line, dataset_config, fmt, markdown_table, pick  # noqa: E402
from h2viz.config import Config, MappingConfig, apply_overrides, load_config  # noqa: E402
from h2viz.errors import H2vizError  # noqa: E402
from h2viz.eval.report import training_views  # noqa: E402
from h2viz.mapping.checkpoint import load_checkpoint  # noqa: E402
from h2viz.pipeline import EvalFrames  # noqa: E402
from h2viz.sources.base import make_source  # noqa: E402


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--datasets", default="synthetic", help=f"comma-separated, from {', '.join(DATASETS)}")
    p.add_argument(
        "--run", type=Path, default=None, help="a finished `h2viz map --out` run: its source, and its own field"
    )
    p.add_argument("--steps", type=int, default=3000, help="Adam steps per fit")
    p.add_argument("--batch", type=int, default=1 << 16, help="samples per step")
    p.add_argument("--loss", choices=LOSSES, default="l2", help="l2: what PSNR measures; l1: mapping's colour loss")
    p.add_argument("--render", choices=RENDERS, default="surface", help="volume: pixels rendered as mapping does")
    p.add_argument("--variant", action="append", default=[], help="comma-separated overrides: one more fit")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="overrides for every fit")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: mapping.runtime.threads)")
    return p.parse_args(argv)


def grid_label(m: MappingConfig) -> str:
    """The colour representation in a few words: levels, finest cell and table size."""
    r = m.representation
    finest_mm = 1000 * (r.hash_base_resolution_m or r.voxel_size_m) / r.hash_scale ** (r.hash_levels - 1)
    return f"L={r.hash_levels}, finest {finest_mm:.3g} mm, T=2^{r.hash_log2_size}"


def load_views(cfg: Config) -> SurfaceColours:
    """The scored training views of the configured source, lifted to surface colour samples."""
    source = make_source(cfg.source)
    try:
        frames = EvalFrames.read(source, cfg.eval.n_interpolate)
    finally:
        source.close()
    if not frames.frames:
        raise MissingData(f"{source.describe()}: no frames could be read")
    return surface_colours(training_views(frames.frames, cfg.eval.n_interpolate), cfg.eval.render_downscale)


def fit_rows(name: str, cfg: Config, data: SurfaceColours, args: argparse.Namespace) -> list[list[str]]:
    """One table row per colour representation (the defaults, then each --variant) fitted to `data`."""
    rows = []
    for variant in ["", *args.variant]:
        mapping = apply_overrides(copy.deepcopy(cfg), [v for v in variant.split(",") if v]).mapping
        start = time.perf_counter()

        def progress(p: CeilingPoint, label: str = grid_label(mapping)) -> None:
            print(f"  {label}: step {p.steps}: {p.pooled_psnr_db:.2f} dB pooled", flush=True)

        curve = fit_colour_ceiling(
            data, mapping, args.steps, args.batch, on_report=progress, loss=args.loss, render=args.render
        )
        trend = " -> ".join(fmt(p.pooled_psnr_db) for p in curve)
        scores = [fmt(curve[-1].pooled_psnr_db), fmt(curve[-1].mean_view_psnr_db)]
        rows.append([name, grid_label(mapping), trend, *scores, fmt(time.perf_counter() - start, 0)])
    return rows


def run_row(run: Path, cfg: Config, data: SurfaceColours) -> list[str]:
    """The row of a finished run: its own trained colour field scored at the same true surface points."""
    mapper, _ = load_checkpoint(run / "checkpoint.pt", cfg.mapping)
    pooled, mean_view = score(predict(mapper.field, data.points), data)
    return [run.name, f"{grid_label(cfg.mapping)}, mapped", "-", fmt(pooled), fmt(mean_view), "-"]


def configs(args: argparse.Namespace) -> list[tuple[str, Config]]:
    """(name, config) of each dataset to fit, or of the --run directory's source."""
    if args.run is not None:
        return [(args.run.name, load_config([args.run / "config.yaml"], args.set))]
    out = []
    for name in pick(args.datasets, dict(DATASETS), "dataset"):
        try:
            out.append((name, dataset_config(DATASETS[name], None, args.set)))
        except MissingData as err:
            print(f"{name}: skipped ({err})")
    return out


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.run is not None and not (args.run / "checkpoint.pt").is_file():
        print(f"{args.run / 'checkpoint.pt'} is missing: pass the --out directory of a finished `h2viz map` run")
        return 2
    rows: list[list[str]] = []
    for name, cfg in configs(args):
        torch.set_num_threads(args.threads or cfg.mapping.runtime.threads or torch.get_num_threads())
        try:
            data = load_views(cfg)
        except H2vizError as err:  # a missing or unreadable source: say which, go on with the others
            print(f"{name}: skipped ({err})")
            continue
        print(f"{name}: {len(data.points)} samples from {int(data.view.max()) + 1} views", flush=True)
        if args.run is not None:
            rows.append(run_row(args.run, cfg, data))
        rows += fit_rows(name, cfg, data, args)
    if rows:
        header = ["dataset", "colour grid", "pooled PSNR over the steps dB", "pooled dB", "mean of views dB", "s"]
        print("\n" + markdown_table(header, rows))
        fit = f"{args.steps} Adam steps of {args.batch} samples, {args.loss} loss, {args.render} colour"
        print(f"\n- {fit}; PSNR of the field at the points")
    print(f"\ncommand: {command_line('bench/ceiling.py')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
