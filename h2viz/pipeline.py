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
from h2viz.errors import CheckpointError, H2vizError
from h2viz.eval.mesh_render import MeshRenderer
from h2viz.eval.metrics import mesh_metrics, observed_mask_fn
from h2viz.eval.report import _stride_K, evaluate_images, format_table, load_mesh, write_metrics
from h2viz.mapping.autosave import Autosaver, find_checkpoint, run_progress, run_state
from h2viz.mapping.checkpoint import load_checkpoint, save_checkpoint
from h2viz.mapping.mapper import Mapper
from h2viz.sources.base import FrameSource, make_source
from h2viz.types import FrameStats, RgbdFrame
from h2viz.worker.anytime_run import AnytimeRun, AnytimeTotals
from h2viz.worker.feed import FrameFeed, WorkerSettings, realtime_from_config
from h2viz.worker.run_recording import RunRecorder

log = logging.getLogger("h2viz.map")
MAX_CONSECUTIVE_FAILURES = 3  # frames in a row the mapper may fail on before the run stops (and saves)


@dataclass
class RunResult:
    out_dir: Path
    stats: list[FrameStats]
    metrics: dict[str, Any] = field(default_factory=dict)
    skipped: int = 0
    dropped: int = 0  # real-time mode: frames integration could not keep up with
    refine_s: float = 0.0  # seconds of mapping.optimization.refine_iters steps after the last frame
    record_s: float = 0.0  # seconds the recording cost the run (meshing every frame, handing over steps)
    errors: list[str] = field(default_factory=list)  # failures met on the way (the run kept what was mapped)
    resumed_from: Path | None = None
    anytime: AnytimeTotals | None = None  # real-time mode: frames integrated / dropped, steps, sharpening

    def summary(self) -> str:
        line = f"mapped {len(self.stats)} frames ({self.skipped} skipped, {self.dropped} dropped)"
        if self.anytime is not None:
            a = self.anytime
            line = f"integrated {a.integrated} of {a.arrived} frames ({self.skipped} skipped, {a.dropped} dropped: "
            line += f"{a.passed_over} read too late, {a.overflowed} beyond the backlog"
            line += f"; {a.thinned} fused into their new voxels' fine lattices only while others waited)"
            line += f"; {a.stream_steps} steps during the stream, {a.sharpen_steps} after it ({a.sharpen_s:.1f} s)"
        if self.stats:
            times = np.array([s.map_time_s for s in self.stats])
            line += f"; per-frame time median {np.median(times):.3f} s, p90 {np.percentile(times, 90):.3f} s"
        lines = [line]
        if self.resumed_from is not None:
            lines.append(f"resumed from {self.resumed_from}")
        lines += [f"problem: {e}" for e in self.errors]
        if self.refine_s > 0:
            lines.append(f"refined the map for {self.refine_s:.1f} s (mapping.optimization.refine_iters)")
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


def _open_mapper(cfg: Config, resume: Path | None) -> tuple[Mapper, int, list[FrameStats]]:
    """A fresh mapper, or one restored from a checkpoint (a file, or a run folder's newest) with the index of the last
    frame it mapped and the stats of the frames mapped before it."""
    if resume is None:
        return Mapper(cfg.mapping), -1, []
    mapper, extra = load_checkpoint(resume, cfg.mapping)
    log.info("resuming from %s after frame %s", resume, extra.get("last_index"))
    last_index, stats = run_progress(resume, extra)
    return mapper, last_index, stats


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
    record: bool = False,
) -> RunResult:
    """Map every frame of the configured source (or, in real-time mode, as it arrives at the source's own rate:
    see `_map_anytime`) and write the run's outputs; with `record` (every-frame mode), also a timeline recording
    of the run in out/recording.
    `resume` (a checkpoint, or a run folder: its newest one; the run folder is
    then also the output folder unless cfg.out_dir says otherwise) continues an earlier run and its stats. The
    mapping state is autosaved to the run folder every cfg.autosave frames / seconds; a source that fails mid-stream,
    repeated mapper failures or Ctrl-C end the stream, and what was mapped is kept, saved and evaluated."""
    source = make_source(cfg.source)
    if resume is not None:
        resume_dir = Path(resume) if Path(resume).is_dir() else None
        resume = find_checkpoint(resume)
        if not cfg.out_dir and resume_dir is not None:
            cfg.out_dir = str(resume_dir)
    out = Path(cfg.out_dir) if cfg.out_dir else default_out_dir(cfg)
    out.mkdir(parents=True, exist_ok=True)
    dump_config(cfg, out / "config.yaml")
    mapper, last_index, stats = _open_mapper(cfg, resume)
    realtime = realtime or realtime_from_config(cfg)
    gt = _ground_truth(source, gt_mesh)
    eval_frames = EvalFrames(len(source), cfg.eval.n_interpolate)
    if record and realtime:
        log.warning("--record records every-frame runs; this real-time run is not recorded")
    recorder = _recorder(mapper, cfg, out, len(source)) if record and not realtime else None
    autosave = Autosaver(out, cfg.autosave, mapper.frames_done)
    errors: list[str] = []
    anytime = None
    if realtime:
        bar = tqdm(total=len(source), disable=not progress, unit="frame", dynamic_ncols=True)
        new_stats, anytime = _map_anytime(source, mapper, cfg, eval_frames, (last_index, stats), autosave, errors, bar)
        bar.close()
        stats.extend(new_stats)
        last_index = stats[-1].index if stats else last_index
    else:
        last_index = _map_stream(mapper, source, eval_frames, stats, last_index, autosave, errors, progress, recorder)
    refine_s = _refine(mapper, cfg.mapping.optimization.refine_iters, progress)
    if recorder is not None:
        recorder.finish()
        mapper.mesh_resolution = cfg.mapping.meshing.mesh_resolution  # the written mesh at its own resolution
    mapper.update_mesh()
    mesh = mapper.mesh()
    _save_outputs(mapper, out, last_index, stats, errors)
    metrics = evaluate(mapper, mesh, gt, eval_frames, cfg) if gt is not None else {}
    if metrics:
        write_metrics(metrics, out / "metrics.json")
    totals = anytime.totals if anytime is not None else None
    dropped = totals.dropped if totals is not None else 0
    _write_stats(out / "stats.json", stats, source, totals, refine_s, errors)
    record_s = recorder.seconds if recorder is not None else 0.0
    return RunResult(out, stats, metrics, len(source.skipped), dropped, refine_s, record_s, errors, resume, totals)


def _recorder(mapper: Mapper, cfg: Config, out: Path, total: int) -> RunRecorder:
    """A recorder of this run into out/recording, meshing at the live dashboard's resolution."""
    mapper.mesh_resolution = cfg.viewer.live_mesh_resolution
    return RunRecorder(mapper, out / "recording", total, cfg.viewer.record_fps)


def _map_stream(
    mapper: Mapper,
    source: FrameSource,
    eval_frames: EvalFrames,
    stats: list[FrameStats],
    last_index: int,
    autosave: Autosaver,
    errors: list[str],
    progress: bool,
    recorder: RunRecorder | None = None,
) -> int:
    """Map the frames after `last_index`, appending to `stats` and `errors`; returns the last mapped frame's index.
    The stream ends early, keeping what was mapped, when the source fails, the mapper fails on
    MAX_CONSECUTIVE_FAILURES frames in a row, or on Ctrl-C."""
    bar = tqdm(total=len(source), disable=not progress, unit="frame", dynamic_ncols=True)
    frames = iter(enumerate(source))
    failures = 0
    while True:
        try:
            position, frame = next(frames)
        except StopIteration:
            break
        except KeyboardInterrupt:
            errors.append(f"interrupted after frame {last_index}; the map so far is saved")
            break
        except (OSError, H2vizError, ValueError, RuntimeError) as e:  # a file deleted, a bag cut short, ...
            log.exception("the source failed")
            errors.append(
                f"the source failed after frame {last_index} ({type(e).__name__}: {e}); the frames mapped so far are "
                "kept and saved; fix the data and resume this run folder to go on"
            )
            break
        bar.update(position + 1 - bar.n)  # frames read so far
        eval_frames.add(position, frame)
        if frame.index <= last_index:
            continue
        try:
            s = mapper.integrate(frame)
        except KeyboardInterrupt:
            errors.append(f"interrupted during frame {frame.index}; the map up to frame {last_index} is saved")
            break
        except Exception as e:  # noqa: BLE001 - one bad frame must not lose the run
            log.exception("mapping frame %d failed", frame.index)
            failures += 1
            errors.append(f"mapping frame {frame.index} failed ({type(e).__name__}: {e}); the frame was skipped")
            if failures >= MAX_CONSECUTIVE_FAILURES:
                errors.append(f"stopped after {failures} failed frames in a row; the map so far is saved")
                break
            continue
        failures = 0
        stats.append(s)
        if recorder is not None:
            recorder.after_frame(frame, s)
        last_index = frame.index
        bar.set_postfix(t=f"{s.map_time_s:.2f}s", it=s.iterations, vox=s.n_voxels, kf=s.n_keyframes)
        failed = autosave.maybe_save(mapper, mapper.frames_done, lambda: run_state(last_index, stats))  # noqa: B023 - called now
        if failed is not None and failed not in errors:
            errors.append(failed)
    bar.close()
    failed = autosave.wait()  # the last autosave is written before the run goes on
    if failed is not None and failed not in errors:
        errors.append(failed)
    return last_index


def _save_outputs(mapper: Mapper, out: Path, last_index: int, stats: list[FrameStats], errors: list[str]) -> None:
    """mesh.ply and checkpoint.pt; a failed write (disk full) is reported in `errors`, the autosave stays."""
    try:
        mapper.export_mesh(out / "mesh.ply")
    except OSError as e:
        errors.append(f"cannot write {out / 'mesh.ply'} ({e}); free space there and export it from the checkpoint")
    try:
        save_checkpoint(mapper, out / "checkpoint.pt", run_state(last_index, stats))
    except CheckpointError as e:
        errors.append(f"{e}; the last autosave in {out} is kept")


def _map_anytime(
    source: FrameSource,
    mapper: Mapper,
    cfg: Config,
    eval_frames: EvalFrames,
    earlier: tuple[int, list[FrameStats]],
    autosave: Autosaver,
    errors: list[str],
    bar: tqdm,
) -> tuple[list[FrameStats], AnytimeRun]:
    """The source played at its own rate: every frame integrated as it arrives, optimisation between frames, then
    until the loss plateaus (anytime.*), autosaving on the way. A resumed run (`earlier`: its last frame's index and
    its frames' stats) plays the stream from the frame after its last. Ctrl-C ends the run, keeping the map."""
    last_index, stats = earlier
    settings = WorkerSettings(realtime=True, stride=max(1, cfg.source.stride))
    position = _read_mapped(source, last_index, eval_frames)
    feed = FrameFeed(
        source, settings, cfg.source.max_frames, cfg.anytime.backlog_frames, last_index, mapper.prepare_ahead
    )
    run = AnytimeRun(mapper, feed, cfg.anytime, autosave=autosave, earlier=stats)

    def arrived(frame: RgbdFrame) -> bool:
        nonlocal position
        eval_frames.add(position, frame)
        position += 1
        bar.update(position + feed.dropped - bar.n)
        waiting, steps, voxels = feed.frames_waiting(), run.totals.stream_steps, mapper.octree.n_voxels
        bar.set_postfix(steps=steps, waiting=waiting, dropped=feed.dropped, vox=voxels)
        return frame.index > last_index

    mapper.warm_up()  # kernels loaded while the first frames arrive would cost the stream ~30 of them
    feed.start()
    try:
        try:
            run.stream(arrived)
        finally:
            feed.stop()
        run.sharpen()
    except KeyboardInterrupt:
        last = run.stats[-1].index if run.stats else last_index
        errors.append(f"interrupted after frame {last}; the map so far is saved")
    errors.extend(run.errors)
    return run.stats, run


def _read_mapped(source: FrameSource, last_index: int, eval_frames: EvalFrames) -> int:
    """Read the frames a resumed real-time run mapped (up to `last_index`) at once, for the evaluation only, so that
    the stream need not play them; how many of the source's selected frames they are."""
    selected = source.selected()
    for n, (position, key) in enumerate(selected):
        if position > last_index:
            return n
        frame = source.get(position, key)
        if frame is not None:
            eval_frames.add(n, frame)
    return len(selected)


def _refine(mapper: Mapper, iterations: int, progress: bool) -> float:
    """mapping.optimization.refine_iters more steps over the keyframes after the last frame; their seconds."""
    if iterations <= 0:
        return 0.0
    start = time.perf_counter()
    with tqdm(total=iterations, disable=not progress, unit="step", desc="refining", dynamic_ncols=True) as bar:
        mapper.refine(iterations, on_step=lambda: bar.update(1))
    return time.perf_counter() - start


def _write_stats(
    path: Path,
    stats: list[FrameStats],
    source: FrameSource,
    anytime: AnytimeTotals | None,
    refine_s: float,
    errors: list[str],
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
        "errors": errors,
    }
    try:
        path.write_text(json.dumps(doc, indent=1))
    except OSError as e:
        log.error("cannot write %s (%s); the checkpoint holds the same frame statistics", path, e)
