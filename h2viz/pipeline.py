"""Headless mapping run (`h2viz map`): source -> mapper -> mesh.ply, checkpoint.pt, config.yaml, stats.json,
metrics.json."""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from tqdm import tqdm

from h2viz.config import Config, dump_config
from h2viz.eval.mesh_render import MeshRenderer
from h2viz.eval.metrics import mesh_metrics, observed_mask_fn
from h2viz.eval.report import _stride_K, evaluate_images, format_table, load_mesh, write_metrics
from h2viz.mapping.checkpoint import load_checkpoint, save_checkpoint
from h2viz.mapping.mapper import Mapper
from h2viz.sources.base import FrameSource, make_source
from h2viz.types import FrameStats, RgbdFrame
from h2viz.worker.anytime_run import AnytimeRun, AnytimeTotals
from h2viz.worker.feed import FrameFeed, WorkerSettings, realtime_from_config

log = logging.getLogger("h2viz.map")


@dataclass
class RunResult:
    out_dir: Path
    stats: list[FrameStats]
    metrics: dict[str, Any] = field(default_factory=dict)
    skipped: int = 0
    dropped: int = 0  # real-time mode: frames integration could not keep up with
    refine_s: float = 0.0  # seconds of mapping.refine_iters steps after the last frame
    anytime: AnytimeTotals | None = None  # real-time mode: frames integrated / dropped, steps, sharpening

    def summary(self) -> str:
        line = f"mapped {len(self.stats)} frames ({self.skipped} skipped, {self.dropped} dropped)"
        if self.anytime is not None:
            a = self.anytime
            line = f"integrated {a.integrated} of {a.arrived} frames ({self.skipped} skipped, {a.dropped} dropped: "
            line += f"{a.passed_over} read too late, {a.overflowed} beyond the backlog)"
            line += f"; {a.stream_steps} steps during the stream, {a.sharpen_steps} after it ({a.sharpen_s:.1f} s)"
        if self.stats:
            times = np.array([s.map_time_s for s in self.stats])
            line += f"; per-frame time median {np.median(times):.3f} s, p90 {np.percentile(times, 90):.3f} s"
        lines = [line]
        if self.refine_s > 0:
            lines.append(f"refined the map for {self.refine_s:.1f} s (mapping.refine_iters)")
        if self.metrics:
            lines.append(format_table(self.metrics))
        lines.append(f"outputs in {self.out_dir}")
        return "\n".join(lines)


class EvalFrames:
    """What evaluation needs from the stream: a few full frames and every frame's coarse depth for culling."""

    def __init__(self, n_total: int, n_keep: int) -> None:
        self.every = max(1, n_total // max(1, 2 * n_keep))
        self.frames: list[RgbdFrame] = []
        self.coarse: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    @classmethod
    def read(cls, source: FrameSource, n_keep: int) -> EvalFrames:
        """Every frame of `source` read once (as `h2viz map` meets them), keeping what evaluation needs."""
        frames = cls(len(source), n_keep)
        for position, frame in enumerate(source):
            frames.add(position, frame)
        return frames

    def add(self, position: int, frame: RgbdFrame) -> None:
        if position % self.every == 0:
            self.frames.append(frame)
        self.coarse.append((_stride_K(frame.K, 4), frame.T_world_camera, frame.depth_m[::4, ::4].copy()))


def default_out_dir(cfg: Config) -> Path:
    return Path("outputs") / f"{cfg.source.format}-{time.strftime('%Y%m%d-%H%M%S')}"


def _open_mapper(cfg: Config, resume: Path | None) -> tuple[Mapper, int]:
    """A fresh mapper, or one restored from a checkpoint with the index of the last frame it mapped."""
    if resume is None:
        return Mapper(cfg.mapping), -1
    mapper, extra = load_checkpoint(resume, cfg.mapping)
    log.info("resuming from %s after frame %s", resume, extra.get("last_index"))
    return mapper, int(extra.get("last_index", -1))


def _ground_truth(source: FrameSource, gt_mesh: Path | None) -> trimesh.Trimesh | None:
    return load_mesh(gt_mesh) if gt_mesh is not None else source.ground_truth_mesh()


def evaluate(
    mapper: Mapper, mesh: trimesh.Trimesh, gt: trimesh.Trimesh | None, frames: EvalFrames, cfg: Config
) -> dict:
    """Mesh metrics against ground truth (culled to what was observed) and image metrics."""
    metrics: dict[str, Any] = {}
    if gt is not None and len(mesh.faces):
        mask = observed_mask_fn(frames.coarse) if cfg.eval.cull_to_observed else None
        metrics["mesh"] = mesh_metrics(mesh, gt, cfg.eval.n_points, cfg.eval.threshold_m, mask)
    if frames.frames:
        gt_render = MeshRenderer(gt) if gt is not None else None
        metrics.update(evaluate_images(mapper.render, frames.frames, cfg.eval, gt_render))
    return metrics


def run_map(
    cfg: Config,
    resume: Path | None = None,
    gt_mesh: Path | None = None,
    progress: bool = True,
    realtime: bool = False,
) -> RunResult:
    """Map every frame of the configured source (or, in real-time mode, as it arrives at the source's own rate:
    see `_map_anytime`) and write the run's outputs."""
    source = make_source(cfg.source)
    out = Path(cfg.out_dir) if cfg.out_dir else default_out_dir(cfg)
    out.mkdir(parents=True, exist_ok=True)
    dump_config(cfg, out / "config.yaml")
    mapper, last_index = _open_mapper(cfg, resume)
    realtime = realtime or realtime_from_config(cfg)
    gt = _ground_truth(source, gt_mesh)
    total = len(source)
    eval_frames = EvalFrames(total, cfg.eval.n_interpolate)
    bar = tqdm(total=total, disable=not progress, unit="frame", dynamic_ncols=True)
    anytime = None
    if realtime:
        stats, anytime = _map_anytime(source, mapper, cfg, eval_frames, last_index, bar)
        last_index = stats[-1].index if stats else last_index
    else:
        stats, last_index = _map_every_frame(source, mapper, eval_frames, last_index, bar)
    bar.close()
    refine_s = _refine(mapper, cfg.mapping.refine_iters, progress)
    mapper.update_mesh()
    mesh = mapper.mesh()
    mapper.export_mesh(out / "mesh.ply")
    save_checkpoint(mapper, out / "checkpoint.pt", {"last_index": last_index})
    metrics = evaluate(mapper, mesh, gt, eval_frames, cfg) if gt is not None else {}
    if metrics:
        write_metrics(metrics, out / "metrics.json")
    totals = anytime.totals if anytime is not None else None
    _write_stats(out / "stats.json", stats, source, totals, refine_s)
    dropped = totals.dropped if totals is not None else 0
    return RunResult(out, stats, metrics, len(source.skipped), dropped, refine_s, totals)


def _map_every_frame(
    source: FrameSource, mapper: Mapper, eval_frames: EvalFrames, last_index: int, bar: tqdm
) -> tuple[list[FrameStats], int]:
    """Every frame in order, each with up to mapping.max_iters steps (the paper's protocol)."""
    stats: list[FrameStats] = []
    for position, frame in enumerate(source):
        bar.update(position + 1 - bar.n)  # frames read so far
        eval_frames.add(position, frame)
        if frame.index <= last_index:
            continue
        s = mapper.integrate(frame)
        stats.append(s)
        last_index = frame.index
        bar.set_postfix(t=f"{s.map_time_s:.2f}s", it=s.iterations, vox=s.n_voxels, kf=s.n_keyframes)
    return stats, last_index


def _map_anytime(
    source: FrameSource, mapper: Mapper, cfg: Config, eval_frames: EvalFrames, last_index: int, bar: tqdm
) -> tuple[list[FrameStats], AnytimeRun]:
    """The source played at its own rate: every frame integrated as it arrives, optimisation between frames, then
    until the loss plateaus (anytime.*)."""
    settings = WorkerSettings(realtime=True, stride=max(1, cfg.source.stride))
    feed = FrameFeed(source, settings, cfg.source.max_frames, cfg.anytime.backlog_frames)
    run = AnytimeRun(mapper, feed, cfg.anytime)
    position = 0

    def arrived(frame: RgbdFrame) -> bool:
        nonlocal position
        eval_frames.add(position, frame)
        position += 1
        bar.update(position + feed.dropped - bar.n)
        bar.set_postfix(steps=run.totals.stream_steps, dropped=feed.dropped, vox=mapper.octree.n_voxels)
        return frame.index > last_index

    feed.start()
    try:
        run.stream(arrived)
    finally:
        feed.stop()
    run.sharpen()
    return run.stats, run


def _refine(mapper: Mapper, iterations: int, progress: bool) -> float:
    """mapping.refine_iters more steps over the keyframes after the last frame; their seconds."""
    if iterations <= 0:
        return 0.0
    start = time.perf_counter()
    with tqdm(total=iterations, disable=not progress, unit="step", desc="refining", dynamic_ncols=True) as bar:
        mapper.refine(iterations, on_step=lambda: bar.update(1))
    return time.perf_counter() - start


def _write_stats(
    path: Path, stats: list[FrameStats], source: FrameSource, anytime: AnytimeTotals | None, refine_s: float
) -> None:
    times = [s.map_time_s for s in stats]
    doc = {
        "frames": [dataclasses.asdict(s) for s in stats],
        "summary": {
            "n_frames": len(stats),
            "median_map_time_s": float(np.median(times)) if times else None,
            "p90_map_time_s": float(np.percentile(times, 90)) if times else None,
            "mean_iterations": float(np.mean([s.iterations for s in stats])) if stats else None,
            "dropped_frames": anytime.dropped if anytime is not None else 0,
            "refine_s": refine_s,
        },
        "realtime": None if anytime is None else {**dataclasses.asdict(anytime), "arrived": anytime.arrived},
        "skipped": [dataclasses.asdict(s) for s in source.skipped],
    }
    path.write_text(json.dumps(doc, indent=1))
