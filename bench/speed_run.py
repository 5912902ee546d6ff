"""One run of bench/speed.py (one method on one dataset), in its own process so that its peak memory is its own:
map the frames, time every frame's stages and the periodic mesh updates, read the peak RSS, then evaluate the
result as bench/quality.py does."""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from collections.abc import Callable, Hashable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import torch
import trimesh

from bench.quality import RenderOnly, TsdfMeshFusion
from bench.tsdf_baseline import TsdfConfig, import_open3d
from h2viz.config import Config, load_config
from h2viz.errors import H2vizError
from h2viz.eval.report import Renderer, load_mesh
from h2viz.mapping.backend import resolve_backend
from h2viz.mapping.mapper import INTEGRATION_STAGES, Mapper
from h2viz.pipeline import EvalFrames, evaluate
from h2viz.sources.base import FrameSource, make_source
from h2viz.types import FrameStats, RgbdFrame

STAGES = (*INTEGRATION_STAGES, "sampling", "forward", "backward", "optimiser")
"""The stages `Mapper.integrate` times in `FrameStats.timings`."""


@dataclass
class Run:
    """What one run measured (the warm-up frame apart); the JSON handed from the subprocess back."""

    method: str
    dataset: str
    note: str = ""
    kernels: str = ""
    threads: int = 0
    mesh_every: int = 0
    warmup_map_s: float | None = None
    warmup_mesh_s: float | None = None
    frame_s: list[float] = field(default_factory=list)
    cpu_s: list[float] = field(default_factory=list)  # process CPU time (all threads) of each frame's mapping
    stage_s: dict[str, list[float]] = field(default_factory=dict)
    iterations: list[int] = field(default_factory=list)
    mesh_s: list[float] = field(default_factory=list)
    start_rss_mb: float | None = None
    peak_rss_mb: float | None = None
    metrics: dict[str, Any] = field(default_factory=dict)
    phase_s: dict[str, float] = field(default_factory=dict)  # wall time of setup, mapping, evaluation

    def add(self, stats: FrameStats, cpu_s: float, mesh_s: float | None, iterates: bool) -> None:
        """Record one measured frame (and the mesh update after it, if there was one)."""
        self.frame_s.append(stats.map_time_s)
        self.cpu_s.append(cpu_s)
        for stage in STAGES if stats.timings else ():
            self.stage_s.setdefault(stage, []).append(stats.timings.get(stage, 0.0))
        if iterates:
            self.iterations.append(stats.iterations)
        if mesh_s is not None:
            self.mesh_s.append(mesh_s)


class Method(Protocol):
    """A mapper under test."""

    iterates: bool  # whether FrameStats.iterations means anything

    def integrate(self, frame: RgbdFrame) -> FrameStats: ...

    def update_mesh(self) -> None: ...

    def result(self) -> tuple[trimesh.Trimesh, Renderer]: ...


class H2vizMethod:
    """h2viz's Mapper; meshing = `Mapper.update_mesh()` (the chunks that changed)."""

    iterates = True

    def __init__(self, cfg: Config) -> None:
        self.mapper = Mapper(cfg.mapping)
        self.kernels = "fused numba" if self.mapper.backend.name == "numba" else "pure torch"
        if self.mapper.field.color_bf16 and self.mapper.device.type == "cpu":
            self.kernels += ", bfloat16 colour decoder"

    def integrate(self, frame: RgbdFrame) -> FrameStats:
        return self.mapper.integrate(frame)

    def update_mesh(self) -> None:
        self.mapper.update_mesh()

    def result(self) -> tuple[trimesh.Trimesh, Renderer]:
        return self.mapper.mesh(), self.mapper.render


class TsdfMethod:
    """Open3D TSDF fusion (1 cm voxels, 5-voxel truncation); meshing = a full extraction."""

    iterates = False
    kernels = ""

    def __init__(self, cfg: Config) -> None:
        self.fusion = TsdfMeshFusion(TsdfConfig(depth_max_m=cfg.source.depth_max_m))

    def integrate(self, frame: RgbdFrame) -> FrameStats:
        return FrameStats(
            index=frame.index, map_time_s=self.fusion.integrate(frame), iterations=0, n_voxels=0, n_keyframes=0
        )

    def update_mesh(self) -> None:
        self.fusion.tsdf.mesh()

    def result(self) -> tuple[trimesh.Trimesh, Renderer]:
        return self.fusion.result()


class DeferredEvalFrames(EvalFrames):
    """The evaluation's frames, noted by where to load them again after mapping instead of kept in memory, so
    that they do not count in the mapping's peak memory."""

    def __init__(self, source: FrameSource, n_keep: int) -> None:
        super().__init__(len(source), n_keep)
        self.source = source
        self.where: list[tuple[int, Hashable]] = []

    def note(self, count: int, frame: RgbdFrame, where: tuple[int, Hashable]) -> None:
        kept = len(self.frames)
        self.add(count, frame)  # the coarse depth for culling stays (a 1/16 of the pixels)
        if len(self.frames) > kept:
            self.frames.pop()
            self.where.append(where)

    def reload(self) -> None:
        self.frames = [f for f in (self.source.get(*w) for w in self.where) if f is not None]


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (ru_maxrss), in MiB."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (2**20 if sys.platform == "darwin" else 2**10)  # bytes on macOS, KiB on Linux


def timed(fn: Callable[[], None]) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def map_frames(method: Method, source: FrameSource, run: Run, eval_frames: DeferredEvalFrames) -> None:
    """Map every frame (loading untimed); the first frame and the mesh update after it are the warm-up."""
    count = 0
    for position, key in source.selected():
        frame = source.get(position, key)
        if frame is None:  # unusable; the source recorded why
            continue
        eval_frames.note(count, frame, (position, key))
        cpu_start = time.process_time()
        stats = method.integrate(frame)
        cpu_s = time.process_time() - cpu_start
        due = run.mesh_every > 0 and count % run.mesh_every == 0
        mesh_s = timed(method.update_mesh) if due else None
        if count == 0:
            run.warmup_map_s, run.warmup_mesh_s = stats.map_time_s, mesh_s
        else:
            run.add(stats, cpu_s, mesh_s, method.iterates)
        count += 1
    if count == 0:
        reasons = "; ".join(f"{s.key}: {s.reason}" for s in source.skipped[:3])
        raise H2vizError(f"no usable frames ({reasons or 'the source is empty'}); check the dataset folder")


def measure(run: Run, cfg: Config, gt_mesh: str, quality: bool) -> None:
    """Map, read the peak memory, then (optionally) evaluate."""
    start = time.perf_counter()
    source = make_source(cfg.source)
    try:
        if run.method == "tsdf":  # the method's libraries are loaded before the memory baseline
            import_open3d()
        else:
            resolve_backend(cfg.mapping.runtime.kernels, cfg.mapping.runtime.device)  # imports the kernels
        run.start_rss_mb = peak_rss_mb()
        method: H2vizMethod | TsdfMethod = TsdfMethod(cfg) if run.method == "tsdf" else H2vizMethod(cfg)
        run.kernels, run.threads = method.kernels, torch.get_num_threads()
        eval_frames = DeferredEvalFrames(source, cfg.eval.n_interpolate)
        run.phase_s["setup"] = time.perf_counter() - start
        run.phase_s["mapping"] = timed(lambda: map_frames(method, source, run, eval_frames))
        run.peak_rss_mb = peak_rss_mb()
        if quality:
            run.phase_s["evaluation"] = timed(lambda: evaluate_run(run, method, source, eval_frames, cfg, gt_mesh))
    finally:
        getattr(source, "close", lambda: None)()


def evaluate_run(
    run: Run, method: Method, source: FrameSource, eval_frames: DeferredEvalFrames, cfg: Config, gt_mesh: str
) -> None:
    """bench/quality.py's evaluation of the final map (mesh brought up to date first)."""
    eval_frames.reload()
    gt = load_mesh(Path(gt_mesh)) if gt_mesh else source.ground_truth_mesh()
    mesh, render = method.result()
    run.metrics = evaluate(RenderOnly(render), mesh, gt, eval_frames, cfg)  # type: ignore[arg-type]


def child_main(args: argparse.Namespace) -> int:
    """Entry point of the subprocess: run, then write the Run as JSON to args.result."""
    run = Run(args.method, args.dataset, mesh_every=args.mesh_every)
    try:
        measure(run, load_config([args.child]), args.gt_mesh, not args.no_quality)
    except H2vizError as e:  # missing open3d, unusable frames: a note in the table
        run.note = str(e)
    Path(args.result).write_text(json.dumps(asdict(run)))
    return 0
