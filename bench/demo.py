"""Benchmark of the demo kit: a recorded headless run (`h2viz map --record`) and what sharing it costs: recording
size per 100 mapped frames (each step stores only what changed) and its cost to the run (meshing the changed
chunks after every frame, on the mapping thread), the time `h2viz replay` takes to load a recording
and serve it, the standalone HTML export's time and size, and the seconds per frame of a fly-through video along
the recorded trajectory rendered from the map (`h2viz render-path`).

    .venv/bin/python bench/demo.py                                   # synthetic scene, configs/fast.yaml, 100 frames
    .venv/bin/python bench/demo.py --dataset icl --frames 100 --doc docs/demo.md
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.common import DATASETS, command_line, dataset_config, fmt, markdown_table, pick, write_doc  # noqa: E402
from h2viz.pipeline import run_map  # noqa: E402
from h2viz.render_path import render_run_path  # noqa: E402
from h2viz.viewer.camera_path import trajectory_path  # noqa: E402
from h2viz.viewer.html_export import export_html  # noqa: E402
from h2viz.viewer.recording import Recording  # noqa: E402
from h2viz.viewer.replay import ReplayServer  # noqa: E402


def measure(name: str, frames: int, config: list[str], overrides: list[str], video_frames: int) -> list[str]:
    ds = DATASETS[name]
    cfg = dataset_config(ds, frames, overrides, config)
    with tempfile.TemporaryDirectory() as tmp:
        cfg.out_dir = str(Path(tmp) / "run")
        result = run_map(cfg, progress=False, record=True)
        t0 = time.perf_counter()
        recording = Recording(result.out_dir)
        replay = ReplayServer(recording, port=0)
        load_s = time.perf_counter() - t0
        replay.stop()
        t0 = time.perf_counter()
        html = export_html(result.out_dir)
        html_s = time.perf_counter() - t0
        last = recording.snapshot(len(recording) - 1)
        frame = last.current_frame
        assert frame is not None
        path = trajectory_path(last.trajectory, recording.steps[0].current.K, frame.height)  # type: ignore[union-attr]
        path.width, path.height, path.fps = 320, 240, 30
        path.duration_s = video_frames / path.fps
        path_file = path.save(Path(tmp) / "path.json")
        t0 = time.perf_counter()
        render_run_path(result.out_dir, path_file, progress=False)
        video_s = time.perf_counter() - t0
        n = len(recording)
        per_frame = float(np.median([s.map_time_s for s in result.stats]))
        return [
            name,
            str(n),
            fmt(recording.bytes / 1e6, 1),
            fmt(recording.bytes / 1e6 * 100 / max(n, 1), 1),
            fmt(per_frame, 2),
            fmt(result.record_s / max(n, 1), 2),
            fmt(load_s, 2),
            fmt(html.stat().st_size / 1e6, 1),
            fmt(html_s, 1),
            fmt(video_s / path.n_frames, 2),
        ]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", default="synthetic", help=f"comma-separated, from {', '.join(DATASETS)}")
    parser.add_argument("--frames", type=int, default=100, help="frames mapped and recorded")
    parser.add_argument("--config", action="append", default=None, help="config files (default configs/fast.yaml)")
    parser.add_argument("--video-frames", type=int, default=30, help="frames of the fly-through video (320x240)")
    parser.add_argument("--doc", default="", help="also write the report to this markdown file")
    parser.add_argument("overrides", nargs="*", help="section.key=value")
    args = parser.parse_args()
    config = args.config if args.config is not None else [str(ROOT / "configs" / "fast.yaml")]
    config = [c for c in config if c]
    rows = [
        measure(name, args.frames, config, args.overrides, args.video_frames)
        for name in pick(args.dataset, DATASETS, "dataset")
    ]
    header = [
        "dataset", "steps", "recording MB", "MB / 100 frames", "map s/frame (median)", "recording s/frame",
        "replay load + serve s", "HTML MB", "HTML export s", "video s/frame 320x240",
    ]  # fmt: skip
    table = markdown_table(header, rows)
    report = f"```\n{command_line('bench/demo.py')}\n```\n\n{table}\n"
    print(report)
    if args.doc:
        write_doc(args.doc, "The demo kit: recording size, replay start, HTML export, fly-through video", report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
