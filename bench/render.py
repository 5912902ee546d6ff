"""Novel-view render speed: `Mapper.render` (rgb, depth, normal, prior) at 160x120, 320x240 and 640x480.

Reproduce:  .venv/bin/python bench/render.py                  (maps 20 synthetic frames first, minutes)
            .venv/bin/python bench/render.py --map-cache /tmp/map20.pt   (maps once, then reuses the map)

The map is built from the first --frames frames of the built-in synthetic room with the default configuration
(`h2viz map` would build the same). Each size and mode renders three novel views (mapped poses moved 15 cm
sideways) --repeats times after one warm-up render; the table gives the median and the best wall time, and
the 1-minute load average (other jobs on the machine inflate wall times). --reference also times the
exhaustive render (every 1 cm of every allocated voxel, `render_image_reference`) at the smallest size.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import DATASETS, command_line, dataset_config, markdown_table  # noqa: E402
from h2viz.mapping.checkpoint import load_checkpoint, save_checkpoint  # noqa: E402
from h2viz.mapping.mapper import Mapper  # noqa: E402
from h2viz.mapping.rendering.images import RenderParams, render_image_reference  # noqa: E402
from h2viz.sources.base import make_source  # noqa: E402

SIZES = ((160, 120), (320, 240), (640, 480))
BUDGET_S = {(160, 120): 0.1, (640, 480): 1.5}


def build_map(frames: int, overrides: list[str], cache: Path | None) -> tuple[Mapper, list[Any], float]:
    """The mapper after `frames` synthetic frames, the frames' cameras (K, pose, height, width), and the
    mapping time (0 when the map came from the cache)."""
    cfg = dataset_config(DATASETS["synthetic"], frames, overrides)
    if cache is not None and cache.exists():
        mapper, extra = load_checkpoint(cache, cfg.mapping)
        return mapper, extra["cameras"], 0.0
    mapper, cameras = Mapper(cfg.mapping), []
    start = time.perf_counter()
    for frame in make_source(cfg.source):
        mapper.integrate(frame)
        cameras.append((frame.K, frame.T_world_camera, frame.height, frame.width))
    seconds = time.perf_counter() - start
    if cache is not None:
        save_checkpoint(mapper, cache, {"cameras": cameras})
    return mapper, cameras, seconds


def novel_views(cameras: list[Any]) -> list[tuple[np.ndarray, np.ndarray, int, int]]:
    """Three mapped poses (a quarter, half and three quarters along) moved 15 cm along their x axis."""
    views = []
    for i in (len(cameras) // 4, len(cameras) // 2, 3 * len(cameras) // 4):
        K, T, h, w = cameras[i]
        T = T.copy()
        T[:3, 3] += 0.15 * T[:3, 0]
        views.append((K, T, h, w))
    return views


def scaled(K: np.ndarray, height: int, width: int, to_width: int) -> np.ndarray:
    """K of the same camera at to_width pixels wide (pixel centres kept aligned)."""
    f = to_width / width
    K = K.copy()
    K[:2, :2] *= f
    K[:2, 2] = (K[:2, 2] + 0.5) * f - 0.5
    return K


def time_renders(render: Any, views: list[Any], size: tuple[int, int], mode: str, repeats: int) -> list[float]:
    """Wall seconds of `repeats` renders of every view at `size`, after one warm-up render."""
    w, h = size
    cams = [(scaled(K, vh, vw, w), T) for K, T, vh, vw in views]
    render(*cams[0], h, w, mode)
    seconds = []
    for _ in range(repeats):
        for K, T in cams:
            start = time.perf_counter()
            render(K, T, h, w, mode)
            seconds.append(time.perf_counter() - start)
    return seconds


def reference_render(mapper: Mapper) -> Any:
    """`Mapper.render` through the exhaustive reference path."""

    def render(K: np.ndarray, T: np.ndarray, h: int, w: int, mode: str) -> np.ndarray:
        params = RenderParams.from_config(mapper.cfg, mapper.max_depth_m)
        return render_image_reference(mapper.field, mapper.octree, K, T, h, w, mode, params, backend=mapper.backend)

    return render


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=20, help="synthetic frames mapped before rendering")
    parser.add_argument("--repeats", type=int, default=3, help="renders of each view per size and mode")
    parser.add_argument("--modes", default="rgb,depth,normal,prior", help="comma-separated render modes")
    parser.add_argument("--threads", type=int, default=2, help="torch and numba threads")
    parser.add_argument("--map-cache", type=Path, help="load the map from this checkpoint, or build and save it")
    parser.add_argument("--reference", action="store_true", help="also time the exhaustive render at 160x120")
    parser.add_argument("overrides", nargs="*", help="config overrides, e.g. mapping.representation.priors=false")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    mapper, cameras, map_s = build_map(args.frames, args.overrides, args.map_cache)
    torch.set_num_threads(args.threads)
    views = novel_views(cameras)
    rows = []
    for size in SIZES:
        for mode in args.modes.split(","):
            s = time_renders(mapper.render, views, size, mode, args.repeats)
            budget = BUDGET_S.get(size)
            rows.append([f"{size[0]}x{size[1]}", mode, f"{np.median(s):.3f}", f"{min(s):.3f}", f"{budget or '-'}"])
    if args.reference:
        for mode in args.modes.split(","):
            s = time_renders(reference_render(mapper), views, SIZES[0], mode, 1)
            rows.append(["160x120", f"{mode} (exhaustive)", f"{np.median(s):.3f}", f"{min(s):.3f}", "-"])
    built = f"mapped in {map_s:.0f} s" if map_s else f"loaded from {args.map_cache}"
    print(f"map: {args.frames} synthetic frames, {mapper.octree.n_voxels} voxels ({built})")
    print(f"threads {args.threads}, load average {os.getloadavg()[0]:.1f} at the end\n")
    print(markdown_table(["size", "mode", "median s", "best s", "budget s"], rows))
    print(f"\n{command_line('bench/render.py')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
