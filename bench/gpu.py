"""Mapping on a GPU: per-frame mapping time, whole-map meshing time and render times on the CUDA backend.

Reproduce:  .venv/bin/python bench/gpu.py                       (30 synthetic frames on CUDA, about a minute)
            .venv/bin/python bench/gpu.py --device cpu --frames 5 --set source.synthetic.width=160 ...

Maps the first --frames frames of the built-in synthetic room with the default configuration on --device
(CUDA unless told otherwise; without one the benchmark stops and says so), then meshes the whole map once and
renders rgb and depth at three mapped poses. Times are wall times with the device synchronised; the first frame
(warm-up: allocation, kernel selection) is reported apart from the median and p90.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import DATASETS, command_line, dataset_config, fmt, machine, markdown_table  # noqa: E402
from h2viz.mapping.mapper import Mapper  # noqa: E402
from h2viz.sources.base import make_source  # noqa: E402


def timed(device: torch.device, fn: Callable[[], Any]) -> float:
    """Wall seconds of fn() with the device's queued work finished before and after."""
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    sync()
    start = time.perf_counter()
    fn()
    sync()
    return time.perf_counter() - start


def device_name(device: torch.device) -> str:
    return torch.cuda.get_device_name(device) if device.type == "cuda" else machine()


def run(frames: int, device: str, overrides: list[str]) -> str:
    """Map, mesh and render; returns the markdown report."""
    cfg = dataset_config(DATASETS["synthetic"], frames, [f"mapping.runtime.device={device}", *overrides])
    mapper = Mapper(cfg.mapping)
    dev = mapper.device
    per_frame, cameras = [], []
    for frame in make_source(cfg.source):
        per_frame.append(timed(dev, lambda f=frame: mapper.integrate(f)))
        cameras.append((frame.K, frame.T_world_camera, frame.height, frame.width))
    mesh: list[Any] = []
    mesh_s = timed(dev, lambda: mesh.append(mapper.mesh()))
    renders: dict[str, list[float]] = {"rgb": [], "depth": []}
    for i in (len(cameras) // 4, len(cameras) // 2, 3 * len(cameras) // 4):
        K, T, h, w = cameras[i]
        for mode in renders:
            renders[mode].append(timed(dev, lambda K=K, T=T, h=h, w=w, m=mode: mapper.render(K, T, h, w, m)))
    steady = np.array(per_frame[1:] or per_frame)
    h, w = cameras[0][2], cameras[0][3]
    rows = [
        ["mapping, first frame", fmt(per_frame[0], 3), ""],
        ["mapping, per frame (median)", fmt(float(np.median(steady)), 3), f"frames 2-{len(per_frame)}"],
        ["mapping, per frame (p90)", fmt(float(np.percentile(steady, 90)), 3), ""],
        ["mesh, whole map", fmt(mesh_s, 3), f"{len(mesh[0].faces)} faces, {mapper.octree.n_voxels} voxels"],
        *[[f"render {m} {w}x{h} (median of 3)", fmt(float(np.median(t)), 3), ""] for m, t in renders.items()],
    ]
    table = markdown_table(["stage", "seconds", "note"], rows)
    head = f"Backend {mapper.backend.name} on {device_name(dev)}; torch {torch.__version__}."
    return f"{head}\n\n{table}\n\nReproduce: `{command_line('bench/gpu.py')}`"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30, help="synthetic frames to map (default 30)")
    parser.add_argument("--device", default="cuda", help="torch device (default cuda)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")
    args = parser.parse_args()
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        print("bench/gpu.py: no CUDA device (or a CPU-only torch build); run it where a GPU is at hand, or pass "
              "--device cpu to check the script", file=sys.stderr)  # fmt: skip
        return 2
    print(run(args.frames, args.device, args.set))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
