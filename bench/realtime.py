"""Real-time mapping: sequences played at their own rate (the synthetic room at 30 Hz, the real sequences at their
timestamps) into h2viz's anytime mode, beside every-frame mode and Open3D TSDF fusion, in one markdown table.

Every k-th frame is held out (as bench/heldout.py does) and the others are played from memory at their timestamps
(a camera delivers frames for free; reading them from disk or rendering the synthetic room would compete with
mapping for the CPU). Rows:

- `anytime`: real-time mode (`h2viz map --realtime`): every frame integrated as it arrives, optimisation in the
  time between frames; scored at the end of the stream and after a further 10, 30 and 60 s of optimisation over
  the keyframes (fewer when the loss plateaus first: the row says when it settled);
- `every-frame`: every mapped frame with its mapping.optimization.max_iters steps, at whatever pace that takes
  (the paper's protocol; not real time);
- `tsdf`: Open3D TSDF fusion fed from the same real-time stream (frames it is too slow for are dropped).

Each row: frames integrated / arrived, integration time per frame, optimisation steps, mesh Acc / Comp / Comp
ratio against ground truth (culled to what the mapped frames observed, where the sequence has a mesh) and held-out
PSNR / depth L1 on each method's own rendered pixels (bench/heldout.py's scoring).

    .venv/bin/python bench/realtime.py                                   # synthetic room + redkitchen
    flock /tmp/h2viz-bench.lock .venv/bin/python bench/realtime.py --datasets synthetic --doc docs/realtime.md
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import DATASETS, Dataset, command_line, dataset_config, fmt, markdown_table, pick, write_doc  # noqa: E402
from bench.heldout import frame_view, is_heldout, own_scores  # noqa: E402
from bench.tsdf_baseline import TsdfConfig, TsdfFusion  # noqa: E402
from h2viz.config import Config, SourceConfig  # noqa: E402
from h2viz.errors import H2vizError  # noqa: E402
from h2viz.eval.mesh_render import MeshRenderer  # noqa: E402
from h2viz.eval.metrics import mesh_metrics, observed_mask_fn  # noqa: E402
from h2viz.eval.report import EvalView, Renderer, load_mesh  # noqa: E402
from h2viz.mapping.autosave import Autosaver  # noqa: E402
from h2viz.mapping.mapper import INTEGRATION_STAGES, Mapper  # noqa: E402
from h2viz.pipeline import EvalFrames  # noqa: E402
from h2viz.sources.base import FrameSource, make_source  # noqa: E402
from h2viz.types import FrameStats, RgbdFrame  # noqa: E402
from h2viz.worker.anytime_run import AnytimeRun  # noqa: E402
from h2viz.worker.feed import END, FrameFeed, WorkerSettings  # noqa: E402

AFTER_S = "10,30,60"
"""Seconds of optimisation after the stream at which the anytime map is scored again (--after)."""

COLUMNS = ["sequence", "method", "scored", "integrated / arrived", "integration ms (median / p90)", "steps"]
COLUMNS += ["Acc (cm)", "Comp (cm)", "Comp ratio (%)", "held-out PSNR (dB)", "held-out depth L1 (cm)"]


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


class ReplaySource(FrameSource):
    """Frames already in memory, delivered at their own timestamps (loading costs nothing)."""

    format_name = "replay"

    def __init__(self, frames: Sequence[RgbdFrame]) -> None:
        super().__init__(SourceConfig())
        self.frames = list(frames)

    def keys(self) -> Sequence[Hashable]:
        return list(range(len(self.frames)))

    def timestamp(self, position: int, key: Hashable) -> float:
        return float(self.frames[int(key)].timestamp)  # type: ignore[call-overload]

    def load(self, position: int, key: Hashable) -> RgbdFrame:
        return self.frames[int(key)]  # type: ignore[call-overload]

    def postprocess(self, frame: RgbdFrame) -> RgbdFrame:
        return frame  # the sequence's own source post-processed it already


@dataclass
class Stream:
    """One sequence, split: the frames played (in memory), the held-out views, what culls the ground truth."""

    cfg: Config
    played: list[RgbdFrame]
    held: list[EvalView]
    gt: trimesh.Trimesh | None
    cull: EvalFrames

    @property
    def duration_s(self) -> float:
        return self.played[-1].timestamp - self.played[0].timestamp if self.played else 0.0


def open_stream(ds: Dataset, args: argparse.Namespace) -> Stream:
    cfg = dataset_config(ds, args.frames, args.set)
    source = make_source(cfg.source)
    played: list[RgbdFrame] = []
    held: list[EvalView] = []
    cull = EvalFrames(len(source), 0)
    try:
        for position, frame in enumerate(source):
            if is_heldout(position, args.k):
                held.append(frame_view(frame))
            else:
                played.append(frame)
                cull.add(position, frame)
        gt_path = ds.gt_mesh_path()
        gt = load_mesh(gt_path) if gt_path is not None else source.ground_truth_mesh()
    finally:
        getattr(source, "close", lambda: None)()
    if not played:
        raise H2vizError(f"{ds.name}: no frames to play")
    return Stream(cfg, played, held, gt, cull)


@dataclass
class Row:
    sequence: str
    method: str
    scored: str = ""
    integrated: int = 0
    arrived: int = 0
    frame_ms: list[float] = field(default_factory=list)
    steps: int | None = None
    scores: dict[str, float] = field(default_factory=dict)
    note: str = ""

    def cells(self) -> list[str]:
        times = np.array(self.frame_ms) if self.frame_ms else None
        timing = "-" if times is None else f"{np.median(times):.0f} / {np.percentile(times, 90):.0f}"
        s = self.scores
        values = [s.get("acc_cm"), s.get("comp_cm"), s.get("comp_ratio"), s.get("psnr_db"), s.get("depth_l1_cm")]
        counts = f"{self.integrated} / {self.arrived}" if self.arrived else "-"
        steps = "-" if self.steps is None else str(self.steps)
        cells = [fmt(v, d) for v, d in zip(values, [2, 2, 1, 2, 2], strict=True)]
        return [self.sequence, self.method, self.scored, counts, timing, steps, *cells]


def score(stream: Stream, mesh: trimesh.Trimesh, render: Renderer, downscale: int) -> dict[str, float]:
    """Mesh metrics against the ground truth (culled to what the played frames observed) and held-out scores."""
    out: dict[str, float] = {}
    if stream.gt is not None and len(mesh.faces):
        c = stream.cfg.eval
        m = mesh_metrics(mesh, stream.gt, c.n_points, c.threshold_m, observed_mask_fn(stream.cull.coarse))
        out.update({k: float(m[k]) for k in ("acc_cm", "comp_cm", "comp_ratio")})
    if stream.held:
        held = own_scores(render, stream.held, downscale)
        out.update({"psnr_db": held["psnr_db"], "depth_l1_cm": held["depth_l1_cm"]})
    return out


def run_anytime(
    stream: Stream,
    name: str,
    downscale: int,
    after_s: Sequence[float],
    autosave: Path | None = None,
    prepare_ahead: bool = True,
) -> list[Row]:
    """The stream into real-time mode; a row at its end and after each of `after_s` seconds of optimisation.
    `autosave`: a folder to autosave into (autosave.*), as `h2viz map --realtime` does into its run folder;
    `prepare_ahead`: frames prepared on the reader thread (as `h2viz map --realtime` does) or the mapping thread."""
    warm_up(stream)
    mapper = Mapper(stream.cfg.mapping)
    backlog = stream.cfg.anytime.backlog_frames
    settings = WorkerSettings(realtime=True)
    prepare = mapper.prepare_ahead if prepare_ahead else None
    feed = FrameFeed(ReplaySource(stream.played), settings, 0, backlog, prepare=prepare)
    saver = None if autosave is None else Autosaver(autosave, stream.cfg.autosave)
    run = AnytimeRun(mapper, feed, stream.cfg.anytime, autosave=saver)
    _log(f"    anytime: playing {len(stream.played)} frames over {stream.duration_s:.1f} s")
    feed.start()
    try:
        run.stream()
    finally:
        feed.stop()
    frame_ms = [1000.0 * s.map_time_s for s in run.stats]
    t = run.totals

    def row(label: str) -> Row:
        _log(f"    anytime: scoring at {label} ({t.stream_steps + t.sharpen_steps} steps)")
        r = Row(name, "anytime", label, t.integrated, t.arrived, frame_ms, t.stream_steps + t.sharpen_steps)
        r.scores = score(stream, mapper.mesh(), mapper.render, downscale)
        if t.dropped:
            r.note = f"{t.passed_over} frames read too late, {t.overflowed} beyond the backlog"
        if saver is not None:
            r.note = "; ".join(filter(None, [r.note, f"{saver.saves} autosaves (autosave.*)"]))
        if not prepare_ahead:
            r.note = "; ".join(filter(None, [r.note, "frames prepared on the mapping thread"]))
        if t.thinned:
            thinned = f"{t.thinned} frames fused into their new voxels' fine lattices only (anytime.fine_prior_stride)"
            r.note = "; ".join(filter(None, [r.note, thinned]))
        r.note = "; ".join(filter(None, [r.note, stage_note(run.stats)]))
        return r

    rows = [row("end of stream")]
    for after in after_s:
        if run.settled:
            rows[-1].scored += f" (settled after {t.sharpen_s:.0f} s)"
            break
        run.sharpen(seconds=after - t.sharpen_s)
        rows.append(row(f"+{after:.0f} s"))
    if run.settled and "settled" not in rows[-1].scored:
        rows[-1].scored += f" (settled after {t.sharpen_s:.0f} s)"
    return rows


def stage_note(stats: Sequence[FrameStats]) -> str:
    """The median milliseconds of each part of integrating a frame (`INTEGRATION_STAGES`) over the frames."""
    parts = [
        f"{stage.replace('_', ' ')} {1000.0 * float(np.median([s.timings.get(stage, 0.0) for s in stats])):.1f}"
        for stage in INTEGRATION_STAGES
    ]
    return f"integration by stage, median ms: {', '.join(parts)}" if stats else ""


def warm_up(stream: Stream) -> None:
    """Compile the numba kernels (cached on disk) on a throw-away mapper, so that the stream does not wait for it."""
    scratch = Mapper(stream.cfg.mapping)
    scratch.add_frame(stream.played[0])
    scratch.live_step()
    del scratch


def run_every_frame(stream: Stream, name: str, downscale: int) -> Row:
    mapper = Mapper(stream.cfg.mapping)
    _log(f"    every-frame: mapping {len(stream.played)} frames")
    stats = [mapper.integrate(f) for f in stream.played]
    steps = sum(s.iterations for s in stats)
    n = len(stats)
    row = Row(name, "every-frame", "after the last frame", n, n, [1000.0 * s.map_time_s for s in stats], steps)
    row.scores = score(stream, mapper.mesh(), mapper.render, downscale)
    return row


def run_tsdf(stream: Stream, name: str, downscale: int, args: argparse.Namespace) -> Row:
    """TSDF fusion of the real-time stream: each frame as it arrives, those it falls a backlog behind dropped."""
    row = Row(name, "tsdf", "end of stream")
    try:
        tsdf = TsdfFusion(
            TsdfConfig(args.tsdf_voxel_m, args.tsdf_trunc_voxels, depth_max_m=stream.cfg.source.depth_max_m)
        )
    except H2vizError as e:
        row.note = str(e)
        return row
    tsdf.integrate(stream.played[0])  # warm-up, on a fusion of its own
    tsdf = TsdfFusion(tsdf.cfg)
    feed = FrameFeed(ReplaySource(stream.played), WorkerSettings(realtime=True), 0, stream.cfg.anytime.backlog_frames)
    _log("    tsdf: fusing the stream")
    feed.start()
    times: list[float] = []
    try:
        while (item := feed.take(1.0)) is not END:
            if item is not None:
                times.append(1000.0 * tsdf.integrate(item))
    finally:
        feed.stop()
    mesh = tsdf.mesh()
    row.integrated, row.arrived, row.frame_ms = tsdf.frames, tsdf.frames + feed.dropped, times
    if len(mesh.faces):
        row.scores = score(stream, mesh, MeshRenderer(mesh), downscale)
    return row


def run_sequence(ds: Dataset, methods: Sequence[str], args: argparse.Namespace) -> list[Row]:
    try:
        stream = open_stream(ds, args)
    except H2vizError as e:
        return [Row(ds.name, m, note=str(e)) for m in methods]
    downscale = args.downscale or stream.cfg.eval.render_downscale
    autosave = Path(tempfile.mkdtemp(prefix="h2viz-bench-")) if args.autosave else None
    runners: dict[str, Callable[[], list[Row]]] = {
        "anytime": lambda: run_anytime(
            stream, ds.name, downscale, args.after, autosave, not args.prepare_on_mapping_thread
        ),
        "every-frame": lambda: [run_every_frame(stream, ds.name, downscale)],
        "tsdf": lambda: [run_tsdf(stream, ds.name, downscale, args)],
    }
    rows: list[Row] = []
    try:
        for m in methods:
            try:
                rows += runners[m]()
            except H2vizError as e:
                rows.append(Row(ds.name, m, note=str(e)))
    finally:
        if autosave is not None:
            shutil.rmtree(autosave, ignore_errors=True)
    return rows


def report(rows: list[Row], args: argparse.Namespace) -> str:
    lines = [markdown_table(COLUMNS, [r.cells() for r in rows]), ""]
    lines += [
        f"- every {args.k}-th frame held out (bench/heldout.py's split); the others played from memory at their "
        "timestamps; held-out scores on each method's own rendered pixels (anytime and every-frame render their "
        "field, tsdf ray casts its mesh); Acc / Comp culled to what the played frames observed.",
        "- integration ms: anytime = Mapper.add_frame (no optimisation); every-frame = a whole frame with its "
        "steps; tsdf = fusing one frame. steps: optimisation steps in all (anytime: between frames and after the "
        "stream).",
    ]
    lines += [f"- {d}: {DATASETS[d].note}" for d in dict.fromkeys(r.sequence for r in rows)]
    lines += list(dict.fromkeys(f"- {r.method} on {r.sequence}: {r.note}" for r in rows if r.note))  # once a run
    lines += ["", f"command: {command_line('bench/realtime.py')}"]
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--datasets", default="synthetic,redkitchen", help=f"any of {','.join(DATASETS)}")
    p.add_argument("--methods", default="anytime,every-frame,tsdf", help="any of anytime,every-frame,tsdf")
    p.add_argument("--k", type=int, default=10, help="hold out every k-th frame, from position k // 2 (default 10)")
    p.add_argument("--frames", type=int, default=None, help="at most N frames per sequence, before the split")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override for every run")
    p.add_argument("--downscale", type=int, default=None, help="held-out renders at 1/N (default: eval's)")
    p.add_argument(
        "--after", default=AFTER_S, help=f"seconds of optimisation after the stream to score at (default {AFTER_S})"
    )
    p.add_argument(
        "--autosave", action="store_true", help="anytime autosaves (autosave.*) as `h2viz map --realtime` does"
    )
    p.add_argument(
        "--prepare-on-mapping-thread",
        action="store_true",
        help="anytime: prepare each frame (rays, voxels to allocate) on the mapping thread, not the reader's",
    )
    p.add_argument("--doc", default=None, help="also write the table, with commit and CPU, to this page")
    p.add_argument("--tsdf-voxel-m", type=float, default=0.01, help="TSDF voxel size (default 1 cm)")
    p.add_argument("--tsdf-trunc-voxels", type=float, default=5.0, help="TSDF truncation in voxels (default 5)")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        args.after = sorted(float(a) for a in args.after.split(",") if a.strip())
    except ValueError as e:
        raise SystemExit(f"--after {args.after!r}: give seconds separated by commas, e.g. 10,30,60") from e
    if args.k < 2:
        raise SystemExit(f"--k {args.k}: use k >= 2 (every k-th frame is held out, the others are played)")
    methods = pick(args.methods, dict.fromkeys(["anytime", "every-frame", "tsdf"]), "method")
    rows: list[Row] = []
    for name in pick(args.datasets, DATASETS, "dataset"):
        _log(f"{name}: {', '.join(methods)} ...")
        start = time.perf_counter()
        rows += run_sequence(DATASETS[name], methods, args)
        _log(f"    done in {time.perf_counter() - start:.0f} s")
    text = report(rows, args)
    print(text)
    if args.doc:
        write_doc(args.doc, "Real-time mapping", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
