"""Soak and crash benchmark: long dashboard runs of the synthetic room with three wire-level clients connected.

Each run is a process of its own (the dashboard, its mapping worker, three REMOTE_CLIENT readers), sampling every
`--sample-every` frames its resident memory, the keyframe store's size and the frame time. Runs:

- revisit: `--frames` frames going `--laps` times round the room's loop (the map stops growing after the first lap);
- explore: `--frames` frames along one loop sampled that finely (the map grows the whole run); `--no-explore` skips it;
- crash: the revisit run again, killed with SIGKILL at a random frame, then resumed from its run folder with
  `--resume`: frames lost (mapped before the kill, not in the autosave) and the final mesh against the revisit run's.

Prints markdown tables with the command that reproduces them, draws the samples in a PNG and, with --doc, writes them
to docs/soak.md. Run it under the shared lock: `flock /tmp/h2viz-bench.lock .venv/bin/python bench/soak.py`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Hashable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as `python bench/soak.py` from anywhere

from bench.common import ROOT, command_line, fmt, markdown_table, write_doc  # noqa: E402
from h2viz.config import Config, apply_overrides, load_config  # noqa: E402
from h2viz.sources.base import FrameSource  # noqa: E402
from h2viz.sources.synthetic import SyntheticSource  # noqa: E402
from h2viz.types import RgbdFrame  # noqa: E402

CLIENTS = 3
TIMEOUT_S = 4 * 3600


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=1000, help="frames of each run")
    p.add_argument("--laps", type=int, default=4, help="loops round the room in the revisit run")
    p.add_argument("--width", type=int, default=160, help="image width (height = 3/4 of it)")
    p.add_argument("--stride", type=int, default=1, help="use every k-th frame of the sequence")
    p.add_argument("--sample-every", type=int, default=25, help="frames between two samples")
    p.add_argument("--budget-mb", type=float, default=32.0, help="mapping.keyframes.keyframe_budget_mb of the runs")
    p.add_argument("--autosave-every", type=int, default=25, help="autosave.every_frames of the runs")
    p.add_argument("--seed", type=int, default=0, help="seed of the frame the crash run is killed at")
    p.add_argument("--no-explore", action="store_true", help="skip the explore run")
    p.add_argument("--out", default="outputs/soak", help="folder of the runs, samples and plot")
    p.add_argument("--reuse", action="store_true", help="keep the runs already finished in --out, run the others")
    p.add_argument("--doc", default="", help="also write the report to this markdown file (docs/soak.md)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="more config overrides")
    p.add_argument("--side-by-side", action="store_true",
                   help="run the crash run beside the others instead of after them (sooner; the runs then share "
                        "the cores, so their frame times are not each run's own)")  # fmt: skip
    p.add_argument("--child", default="", help=argparse.SUPPRESS)  # run folder of a child process
    p.add_argument("--child-laps", type=int, default=1, help=argparse.SUPPRESS)
    p.add_argument("--resume", action="store_true", help=argparse.SUPPRESS)
    return p.parse_args(argv)


# ------------------------------------------------------------------------------------------- the runs' process


class LapSource(FrameSource):
    """The synthetic room's loop played `laps` times: frame lap * n + i is frame i of the loop again."""

    format_name = "synthetic-laps"

    def __init__(self, cfg: Config, laps: int) -> None:
        super().__init__(cfg.source)
        self.room, self.laps = SyntheticSource(cfg.source), laps
        self.n = cfg.source.synthetic.n_frames

    def keys(self) -> Sequence[Hashable]:
        return list(range(self.n * self.laps))

    def load(self, position: int, key: Hashable) -> RgbdFrame:
        frame = self.room.render_frame(int(key) % self.n)  # type: ignore[call-overload]
        return dataclasses.replace(frame, index=int(key))  # type: ignore[call-overload]

    def ground_truth_mesh(self) -> Any:
        return None  # no live metrics: they would cost the run time the benchmark does not measure


def run_config(args: argparse.Namespace, frames_per_lap: int) -> Config:
    cfg = load_config()
    overrides = [
        f"source.synthetic.width={args.width}",
        f"source.synthetic.height={args.width * 3 // 4}",
        f"source.synthetic.n_frames={frames_per_lap}",
        f"source.stride={args.stride}",
        "source.synthetic.prefetch=0",
        f"mapping.keyframes.keyframe_budget_mb={args.budget_mb}",
        f"autosave.every_frames={args.autosave_every}",
        "autosave.every_s=0",
        *args.set,
    ]
    return apply_overrides(cfg, overrides)


def child(args: argparse.Namespace) -> None:
    """One run: dashboard + worker + CLIENTS wire readers; samples to <folder>/samples.jsonl, progress to
    <folder>/progress (frames mapped), the final mesh to <folder>/mesh.ply."""
    from bench.viewer import REMOTE_CLIENT
    from h2viz.viewer.server import Dashboard, build_worker
    from h2viz.worker.mapping_worker import rss_mb

    folder = Path(args.child)
    cfg = run_config(args, args.frames // args.child_laps)
    cfg.out_dir = str(folder)
    worker = build_worker(cfg, folder if args.resume else None, LapSource(cfg, args.child_laps))
    dashboard = Dashboard(worker, cfg, port=0).start()
    ws_url = dashboard.url.replace("http://", "ws://")
    readers = [subprocess.Popen([sys.executable, "-c", REMOTE_CLIENT, ws_url], stdout=subprocess.DEVNULL)
               for _ in range(CLIENTS)]  # fmt: skip
    deadline = time.time() + 120
    while dashboard.client_count() < CLIENTS and time.time() < deadline:
        time.sleep(0.1)
    samples = open(folder / "samples.jsonl", "a")  # noqa: SIM115 - open for the whole run
    worker.start()
    version, next_sample = 0, 0
    while True:
        version, snap = worker.slot.wait_newer(version, 0.2)
        if snap is None:
            continue
        (folder / "progress.tmp").write_text(str(snap.frames_done))
        (folder / "progress.tmp").replace(folder / "progress")  # atomic: a kill never leaves it half written
        if snap.frames_done >= next_sample and snap.stats:
            times = [s.map_time_s for s in list(snap.stats)[-args.sample_every :]]
            row = {
                "frame": snap.frames_done,
                "rss_mb": rss_mb(),
                "keyframe_mb": snap.stats[-1].keyframe_mb,
                "view_mb": snap.stats[-1].view_mb,
                "keyframes": snap.stats[-1].n_keyframes,
                "voxels": snap.stats[-1].n_voxels,
                "frame_s": float(np.median(times)),
                "surface_m2": float(sum(_area(c.vertices, c.faces) for c in snap.chunks.values())),
                "clients": dashboard.client_count(),
            }
            samples.write(json.dumps(row) + "\n")
            samples.flush()
            next_sample = (snap.frames_done // args.sample_every + 1) * args.sample_every
        if snap.finished:
            break
    (folder / "mesh.ply").write_bytes(worker.submit("export", format="ply").result(600))
    summary = {
        "frames": snap.frames_done,
        "max_keyframe_mb": max(s.keyframe_mb for s in snap.stats),
        "budget": dataclasses.asdict(worker.mapper.keyframe_budget.report),
        "errors": list(worker.errors),
    }
    (folder / "summary.json").write_text(json.dumps(summary))
    for reader in readers:
        reader.terminate()
    dashboard.stop()
    worker.stop()


def _area(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Surface area (m²) of a triangle mesh (V,3) / (F,3)."""
    if len(faces) == 0:
        return 0.0
    v = np.asarray(vertices, np.float64)[np.asarray(faces)]  # (F,3,3)
    return float(0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum())


# ----------------------------------------------------------------------------------------------- the parent


def spawn(args: argparse.Namespace, folder: Path, laps: int, resume: bool = False) -> subprocess.Popen[bytes]:
    folder.mkdir(parents=True, exist_ok=True)
    argv = [sys.executable, str(Path(__file__).resolve()), "--child", str(folder), "--child-laps", str(laps)]
    passed = ["--frames", str(args.frames), "--width", str(args.width), "--stride", str(args.stride),
              "--sample-every", str(args.sample_every), "--budget-mb", str(args.budget_mb),
              "--autosave-every", str(args.autosave_every)]  # fmt: skip
    for item in args.set:
        passed += ["--set", item]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    log = open(folder / "run.log", "ab")  # noqa: SIM115 - the child's output, kept with its folder
    return subprocess.Popen([*argv, *passed, *(["--resume"] if resume else [])], cwd=ROOT, env=env,
                            stdout=log, stderr=subprocess.STDOUT)  # fmt: skip


def finish(proc: subprocess.Popen[bytes], folder: Path) -> None:
    if proc.wait(TIMEOUT_S) != 0:
        raise SystemExit(f"the run in {folder} failed (exit {proc.returncode}); see {folder / 'run.log'}")


def read_samples(folder: Path) -> list[dict[str, Any]]:
    path = folder / "samples.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines()] if path.is_file() else []


def progress(folder: Path) -> int:
    try:
        return int((folder / "progress").read_text() or 0)
    except (OSError, ValueError):
        return 0


def crash_or_earlier(args: argparse.Namespace, out: Path) -> dict[str, Any]:
    """The crash run's outcome: the one `out` holds from an earlier invocation, else a new crash run's."""
    if (out / "crash.json").is_file():
        return json.loads((out / "crash.json").read_text())
    shutil.rmtree(out / "crash", ignore_errors=True)
    crash = crash_run(args, out / "crash", args.laps)
    (out / "crash.json").write_text(json.dumps(crash))
    return crash


def crash_run(args: argparse.Namespace, folder: Path, laps: int) -> dict[str, Any]:
    """The revisit run killed with SIGKILL at a random frame, then resumed from its run folder."""
    from h2viz.mapping.autosave import find_checkpoint
    from h2viz.mapping.checkpoint import load_checkpoint

    total = args.frames // args.stride
    kill_at = int(np.random.default_rng(args.seed).integers(min(args.autosave_every + 1, total - 1), total - 1))
    proc = spawn(args, folder, laps)
    while progress(folder) < kill_at and proc.poll() is None:
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()  # its wire readers end by themselves when the server's sockets close
    mapped = progress(folder)
    saved = find_checkpoint(folder)
    kept = load_checkpoint(saved)[0].frames_done
    resumed = spawn(args, folder, laps, resume=True)
    finish(resumed, folder)
    return {"kill_at": kill_at, "mapped": mapped, "kept": kept, "lost": mapped - kept, "checkpoint": saved.name}


def mesh_match(a_path: Path, b_path: Path) -> dict[str, float]:
    """Face counts and vertex distances both ways between two meshes (the bag-vs-folder test's measures)."""
    import trimesh
    from scipy.spatial import cKDTree

    a = trimesh.load(a_path, process=False)
    b = trimesh.load(b_path, process=False)
    d_ab, _ = cKDTree(b.vertices).query(a.vertices)
    d_ba, _ = cKDTree(a.vertices).query(b.vertices)
    return {
        "faces_a": len(a.faces),
        "faces_b": len(b.faces),
        "face_diff": abs(len(a.faces) - len(b.faces)) / max(1, len(a.faces)),
        "median_mm": 1000 * max(float(np.median(d_ab)), float(np.median(d_ba))),
        "p99_mm": 1000 * max(float(np.percentile(d_ab, 99)), float(np.percentile(d_ba, 99))),
    }


def growth(samples: list[dict[str, Any]], start: int, window: int, key: str = "rss_mb") -> tuple[float, float, float]:
    """Median of `key` over the samples of frames [start, start + window), over the samples of the last `window`
    frames, and the relative growth between the two (medians: a sample can fall on a passing peak, an autosave or
    a mesh job)."""
    end = samples[-1]["frame"]
    first = [s[key] for s in samples if start <= s["frame"] < start + window] or [samples[-1][key]]
    last = [s[key] for s in samples if s["frame"] > end - window]
    a, b = float(np.median(first)), float(np.median(last))
    return a, b, (b - a) / a if a else float("nan")


COLOURS = {"revisit": (200, 90, 30), "explore": (40, 140, 40), "crash": (30, 30, 210)}  # BGR


def _text(image: np.ndarray, s: str, org: tuple[int, int], colour: tuple[int, int, int] = (0, 0, 0)) -> None:
    cv2.putText(image, s, org, cv2.FONT_HERSHEY_SIMPLEX, 0.4, colour, 1, cv2.LINE_AA)


def _panel(image: np.ndarray, box: tuple[int, int, int, int], runs: dict[str, list[dict[str, Any]]], key: str,
           title: str, n_max: int, level: float | None) -> None:  # fmt: skip
    """One line plot of `key` against frames in the pixel box (x0, y0, w, h); `level` a grey horizontal line."""
    x0, y0, w, h = box
    values = [s[key] for rows in runs.values() for s in rows] + ([level] if level is not None else [])
    top = max(values, default=1.0) * 1.1 or 1.0

    def to_px(frame: float, value: float) -> tuple[int, int]:
        return int(x0 + w * frame / n_max), int(y0 + h - h * value / top)

    cv2.rectangle(image, (x0, y0), (x0 + w, y0 + h), (0, 0, 0), 1)
    _text(image, title, (x0, y0 - 8))
    _text(image, f"{top:.3g}", (x0 - 44, y0 + 10))
    _text(image, "0", (x0 - 14, y0 + h))
    _text(image, f"frame {n_max}", (x0 + w - 70, y0 + h + 16))
    if level is not None:
        cv2.line(image, to_px(0, level), to_px(n_max, level), (120, 120, 120), 1, cv2.LINE_AA)
    for i, (name, rows) in enumerate(runs.items()):
        colour = COLOURS.get(name, (0, 0, 0))
        points = np.array([to_px(s["frame"], s[key]) for s in rows], np.int32)
        if len(points) > 1:
            cv2.polylines(image, [points], False, colour, 2, cv2.LINE_AA)
        _text(image, name, (x0 + 8, y0 + 16 + 14 * i), colour)


def plot(runs: dict[str, list[dict[str, Any]]], budget_mb: float, path: Path) -> Path:
    """Resident memory and keyframe store (MB) and frame time (s) against frames, one panel each, drawn with OpenCV
    (the budget as a grey line)."""
    panels = [("resident memory, MB", "rss_mb"), ("keyframe store, MB", "keyframe_mb"), ("frame time, s", "frame_s")]
    w, h, pad = 420, 260, 64
    image = np.full((h + 2 * pad, len(panels) * (w + pad) + pad, 3), 255, np.uint8)
    n_max = max((s["frame"] for rows in runs.values() for s in rows), default=1)
    for p, (title, key) in enumerate(panels):
        level = budget_mb if key == "keyframe_mb" else None
        _panel(image, (pad + p * (w + pad), pad, w, h), runs, key, title, n_max, level)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), image)
    return path


def report(args: argparse.Namespace, runs: dict[str, list[dict[str, Any]]], summaries: dict[str, dict[str, Any]],
           crash: dict[str, Any], match: dict[str, float], png: Path) -> str:  # fmt: skip
    lines = [f"`{command_line('bench/soak.py')}`", ""]
    total = args.frames // args.stride
    lines.append(
        f"Synthetic room, {args.width}x{args.width * 3 // 4}, {total} frames a run, {CLIENTS} wire-level dashboard "
        f"clients, mapping.keyframes.keyframe_budget_mb={args.budget_mb:g}, autosave every {args.autosave_every} frames"
        + (f", {' '.join(args.set)}" if args.set else "")
        + f". Samples every {args.sample_every} frames; plot: {png.name}."
    )
    lines.append("")
    header = ["run", "frame", "RSS MB", "keyframes MB", "views MB", "keyframes", "voxels", "surface m²", "frame s"]
    rows = []
    for name, samples in runs.items():
        step = max(1, len(samples) // 10)
        for s in samples[::step] + ([samples[-1]] if (len(samples) - 1) % step else []):
            rows.append([name, str(s["frame"]), fmt(s["rss_mb"], 0), fmt(s["keyframe_mb"], 1), fmt(s["view_mb"], 1),
                         str(s["keyframes"]),
                         str(s["voxels"]), fmt(s["surface_m2"], 1), fmt(s["frame_s"], 3)])  # fmt: skip
    lines += [markdown_table(header, rows), ""]
    start, window = min(300, total // 3), max(total // 10, 2 * args.sample_every)
    first, last, rel = growth(runs["revisit"], start, window)
    top = max(s["rss_mb"] for s in runs["revisit"] if s["frame"] >= start)
    budget = summaries["revisit"]["budget"]
    peak = max(v["max_keyframe_mb"] for v in summaries.values())
    targets = [
        [f"revisit: RSS growth after frame {start} (median of frames {start}-{start + window} vs the last {window})",
         "≤ 10 %", f"{first:.0f} -> {last:.0f} MB ({100 * rel:+.1f} %), largest sample {top:.0f} MB",
         "yes" if rel <= 0.10 else "no"],
        ["keyframe store, largest over every frame of every run", f"≤ {args.budget_mb:g} MB", f"{peak:.1f} MB",
         "yes" if peak <= args.budget_mb else "no"],
        ["keyframes retired / thinned / retired losing coverage (revisit)", "coverage kept",
         f"{budget['retired']} / {budget['thinned']} / {budget['coverage_lost']}",
         "yes" if budget["coverage_lost"] == 0 else "no"],
    ]  # fmt: skip
    if "explore" in runs:
        e = runs["explore"]
        mb0, mb1, _ = growth(e, start, window)
        m2_0, m2_1, _ = growth(e, start, window, "surface_m2")
        d_mb, d_m2 = mb1 - mb0, m2_1 - m2_0
        per = d_mb / d_m2 if d_m2 > 0 else float("nan")
        targets.append([f"explore: RSS growth per m² of new surface after frame {start}", "grows with the surface",
                        f"{d_mb:+.0f} MB for {d_m2:+.1f} m² ({fmt(per, 2)} MB/m²)", "-"])  # fmt: skip
    targets += [
        [f"SIGKILL at frame {crash['kill_at']}: frames lost", f"≤ {args.autosave_every}",
         f"{crash['lost']} ({crash['mapped']} mapped, {crash['kept']} in {crash['checkpoint']})",
         "yes" if crash["lost"] <= args.autosave_every else "no"],
        ["resumed vs uninterrupted mesh: faces differ", "≤ 3 %", f"{100 * match['face_diff']:.2f} %",
         "yes" if match["face_diff"] <= 0.03 else "no"],
        ["resumed vs uninterrupted mesh: vertex distance median / p99", "< 3 / 15 mm",
         f"{match['median_mm']:.2f} / {match['p99_mm']:.2f} mm",
         "yes" if match["median_mm"] < 3 and match["p99_mm"] < 15 else "no"],
    ]  # fmt: skip
    lines += [markdown_table(["target", "wanted", "measured", "met"], targets)]
    errors = [e for v in summaries.values() for e in v["errors"]]
    if errors:
        lines += ["", "Errors the runs reported:", *(f"- {e}" for e in errors)]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> str:
    args = parse_args(argv)
    if args.child:
        child(args)
        return ""
    if args.frames < 3 or args.laps < 1 or args.frames % args.laps:
        raise SystemExit(f"--frames ({args.frames}) must be >= 3 and a multiple of --laps ({args.laps})")
    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not args.reuse:
        raise SystemExit(f"{out} is not empty; pass another --out, remove it, or --reuse its finished runs")
    plan = {"revisit": args.laps} | ({} if args.no_explore else {"explore": 1})
    runs, summaries = {}, {}
    with ThreadPoolExecutor(1) as beside:
        crashed = beside.submit(crash_or_earlier, args, out) if args.side_by_side else None
        for name, laps in plan.items():
            if not (out / name / "summary.json").is_file():
                shutil.rmtree(out / name, ignore_errors=True)  # an unfinished run starts again
                finish(spawn(args, out / name, laps), out / name)
            runs[name] = read_samples(out / name)
            summaries[name] = json.loads((out / name / "summary.json").read_text())
        crash = crashed.result() if crashed is not None else crash_or_earlier(args, out)
    runs["crash"] = read_samples(out / "crash")
    summaries["crash"] = json.loads((out / "crash" / "summary.json").read_text())
    match = mesh_match(out / "revisit" / "mesh.ply", out / "crash" / "mesh.ply")
    png = plot(runs, args.budget_mb, out / "soak.png")
    text = report(args, runs, summaries, crash, match, png)
    print(text)
    if args.doc:
        doc_png = Path(args.doc).with_suffix(".png")
        doc_png.parent.mkdir(parents=True, exist_ok=True)
        doc_png.write_bytes(png.read_bytes())
        print(f"wrote {write_doc(args.doc, 'Soak and crash recovery', text.replace(png.name, doc_png.name))}")
    return text


if __name__ == "__main__":
    main()
