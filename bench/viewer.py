"""Benchmark of the live dashboard: mapping speed with 0, 1 and 3 connected browsers, latency from a
frame being mapped to its mesh change arriving in a browser, bytes per mesh update, and novel-view
render time per resolution. Browsers are Debian's headless chromium driven by Playwright.

    .venv/bin/python bench/viewer.py                      # synthetic scene, configs/fast.yaml, 20 frames
    .venv/bin/python bench/viewer.py --frames 40 mapping.max_iters=10
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from h2viz.config import Config, load_config, source_config_file  # noqa: E402
from h2viz.sources.base import make_source  # noqa: E402
from h2viz.viewer.server import Dashboard  # noqa: E402
from h2viz.viewer.shapes import view_intrinsics  # noqa: E402
from h2viz.viewer.wire import decode_frame  # noqa: E402
from h2viz.worker import MappingWorker  # noqa: E402

CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
]
CHROMIUM_ARGS += ["--no-first-run", "--disable-sync"]
RESOLUTIONS = [(80, 60), (160, 120), (320, 240), (640, 480)]


@dataclass
class Run:
    """What one mapping run with `browsers` connected pages measured."""

    browsers: int
    frames: int = 0
    wall_s: float = 0.0
    map_s: list[float] = field(default_factory=list)
    latencies_s: list[float] = field(default_factory=list)
    extract_s: list[float] = field(default_factory=list)  # frame mapped -> its mesh extracted
    remesh_s: list[float] = field(default_factory=list)  # duration of each mesh extraction
    send_delay_s: list[float] = field(default_factory=list)  # mesh extracted -> dashboard sends it
    transfer_s: list[float] = field(default_factory=list)  # dashboard sends -> browser has all of it
    update_bytes: list[int] = field(default_factory=list)
    update_chunks: list[int] = field(default_factory=list)
    whole_mesh_bytes: int = 0


def timed_mapper(cfg: Config) -> Any:
    """The real Mapper, noting (map version, time) of every mesh update."""
    from h2viz.mapping.mapper import Mapper

    class TimedMapper(Mapper):
        def __init__(self) -> None:
            super().__init__(cfg.mapping)
            self.meshed: list[tuple[int, float, float, int]] = []  # (version, start, end, frames integrated)
            self.integrated = 0

        def integrate(self, frame: Any) -> Any:
            stats = super().integrate(frame)
            self.integrated += 1
            return stats

        def update_mesh(self) -> None:
            t0 = time.time()
            super().update_mesh()
            self.meshed.append((self.version, t0, time.time(), self.integrated))

    return TimedMapper()


def mapping_run(cfg: Config, n_browsers: int, playwright: Any) -> tuple[Run, MappingWorker, Dashboard, Any]:
    run = Run(n_browsers)
    mapper = timed_mapper(cfg)
    worker = MappingWorker(make_source(cfg.source), mapper, cfg)
    dashboard = Dashboard(worker, cfg, port=0)
    sends: list[tuple[float, int, list[str]]] = []  # (time, newest chunk version, node names)

    def on_sent(snap: Any, keys: list[tuple[int, int, int]], nbytes: int) -> None:
        if keys:
            newest = max(snap.chunks[k].version for k in keys)
            sends.append((time.time(), newest, [_name(k) for k in keys]))

    dashboard.layers.mesh.on_sent.append(on_sent)
    arrivals: list[tuple[float, str, int]] = []  # (time, node name, bytes) of GLB messages in page 0
    browser = (
        playwright.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_ARGS)
        if n_browsers
        else None
    )
    pages = (
        [browser.new_page(viewport={"width": 800, "height": 600}) for _ in range(n_browsers)]
        if browser
        else []
    )
    if pages:
        pages[0].on("websocket", lambda ws: ws.on("framereceived", lambda p: _record(p, arrivals)))
    dashboard.start()
    for page in pages:
        page.goto(dashboard.url)
    _wait_clients(dashboard, pages, n_browsers)
    t0 = time.time()
    worker.start()
    while not worker.wait_finished(0.05):
        if pages:
            pages[0].wait_for_timeout(100)
    run.wall_s = time.time() - t0
    if pages:
        pages[0].wait_for_timeout(3000)  # let the last update arrive
    snap = worker.slot.get()[1]
    run.frames = snap.frames_done
    run.map_s = [s.map_time_s for s in snap.stats]
    _latencies(run, worker, mapper, sends, arrivals)
    run.whole_mesh_bytes = sum(len(_glb(c)) for c in snap.chunks.values())
    return run, worker, dashboard, browser


def _name(key: tuple[int, int, int]) -> str:
    return "/mesh/c_" + "_".join(str(int(k)).replace("-", "m") for k in key)


def _glb(chunk: Any) -> bytes:
    from h2viz.viewer.glb import mesh_glb

    return mesh_glb(chunk.vertices, chunk.faces, chunk.colors)


def _record(payload: Any, arrivals: list[tuple[float, str, int]]) -> None:
    now = time.time()
    if isinstance(payload, bytes):
        arrivals.extend(
            (now, m.name, m.nbytes) for m in decode_frame(payload) if m.type == "GlbMessage" and m.name
        )


def _wait_clients(dashboard: Dashboard, pages: list[Any], n: int) -> None:
    deadline = time.time() + 120
    while dashboard.client_count() < n and time.time() < deadline:
        pages[0].wait_for_timeout(200)


def _first_arrivals(names: list[str], t_sent: float, arrivals: list) -> list[tuple[float, int]]:
    """(time, bytes) of the first arrival of each node name at or after `t_sent` (none if one is missing)."""
    first: dict[str, tuple[float, int]] = {}
    for t, n, b in arrivals:  # in arrival order
        if n in names and n not in first and t >= t_sent - 0.01:
            first[n] = (t, b)
    return list(first.values()) if len(first) == len(set(names)) else []


def _latencies(run: Run, worker: MappingWorker, mapper: Any, sends: list, arrivals: list) -> None:
    """Per frame: first browser arrival of a mesh update extracted after the frame was mapped."""
    frame_times = sorted(worker.mapped_at.values())
    received: list[tuple[float, int]] = []  # (arrival of the whole update, newest chunk version)
    for t_sent, version, names in sends:
        got = _first_arrivals(names, t_sent, arrivals)
        if got:
            received.append((max(t for t, _ in got), version))
            run.update_bytes.append(sum(b for _, b in got))
            run.update_chunks.append(len(names))
    run.remesh_s = [t1 - t0 for _, t0, t1, _ in mapper.meshed]
    extracted = {v: t1 for v, _, t1, _ in mapper.meshed}
    run.send_delay_s = [t - extracted[v] for t, v, _ in sends if v in extracted]
    run.transfer_s = [
        max(t for t, _ in got) - t_sent
        for t_sent, _, names in sends
        if (got := _first_arrivals(names, t_sent, arrivals))
    ]
    for i, t_mapped in enumerate(frame_times):
        meshes = [(v, t1) for v, _, t1, n in mapper.meshed if n >= i + 1]  # extractions including frame i
        if not meshes:
            continue
        run.extract_s.append(meshes[0][1] - t_mapped)
        later = [t for t, v in received if v >= meshes[0][0]]
        if later:
            run.latencies_s.append(min(later) - t_mapped)


def render_times(worker: MappingWorker, dashboard: Dashboard) -> list[tuple[str, float, float]]:
    """(resolution, rgb render s, background render s = rgb + half-resolution depth) at the last pose."""
    frame = worker.slot.get()[1].current_frame
    out = []
    for width, height in RESOLUTIONS:
        K = view_intrinsics(2 * np.arctan2(0.5 * frame.height, frame.K[1, 1]), width, height)
        args = {"K": K, "T_world_camera": frame.T_world_camera, "height": height, "width": width}
        rgb = worker.submit("render", mode="rgb", **args).result(600).seconds
        both = (
            worker.submit("render", mode="rgb", with_depth=True, depth_downscale=2, **args)
            .result(600)
            .seconds
        )
        out.append((f"{width}x{height}", rgb, both))
    return out


def _median_max(values: list[float], scale: float = 1.0) -> str:
    if not values:
        return "-"
    return f"{scale * statistics.median(values):.0f} / {scale * max(values):.0f}"


def print_tables(runs: list[Run], renders: list[tuple[str, float, float]], command: str) -> None:
    print(f"\nReproduce: {command}\n")
    print("| browsers | frames | wall s | frames / s | mapper s / frame (median) |")
    print("|---:|---:|---:|---:|---:|")
    for r in runs:
        rate, median = r.frames / r.wall_s, statistics.median(r.map_s)
        print(f"| {r.browsers} | {r.frames} | {r.wall_s:.1f} | {rate:.3f} | {median:.2f} |")
    r = next((r for r in runs if r.browsers == 1), None)
    if r is not None:
        latency = f"frame mapped -> its mesh change in the browser, ms ({len(r.latencies_s)} frames)"
        rows = [
            (latency, _median_max(r.latencies_s, 1000)),
            ("  of which: frame mapped -> its mesh extracted, ms", _median_max(r.extract_s, 1000)),
            ("mesh extraction (update_mesh) duration, ms", _median_max(r.remesh_s, 1000)),
            ("mesh extracted -> dashboard sends it, ms", _median_max(r.send_delay_s, 1000)),
            ("dashboard sends -> browser received the whole update, ms", _median_max(r.transfer_s, 1000)),
            ("mesh updates received", str(len(r.update_bytes))),
            ("kB per mesh update", _median_max([float(b) for b in r.update_bytes], 1e-3)),
            ("chunks per mesh update", _median_max([float(c) for c in r.update_chunks])),
            ("whole final mesh as GLB chunks, kB", f"{r.whole_mesh_bytes / 1e3:.0f}"),
        ]
        print("\n| mesh streaming (1 browser) | median / max |\n|---|---:|")
        for name, value in rows:
            print(f"| {name} | {value} |")
    print("\n| novel view | rgb render ms | background (rgb + half-res depth) ms |\n|---|---:|---:|")
    for res, rgb, both in renders:
        print(f"| {res} | {1000 * rgb:.0f} | {1000 * both:.0f} |")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--frames", type=int, default=20, help="frames mapped per run")
    parser.add_argument("--browsers", type=int, nargs="+", default=[0, 1, 3], help="browser counts to run")
    parser.add_argument("overrides", nargs="*", help="config overrides, e.g. mapping.max_iters=5")
    args = parser.parse_args()
    files = [source_config_file("synthetic"), ROOT / "configs" / "fast.yaml"]
    base = ["source.format=synthetic", "source.stride=4", f"source.max_frames={args.frames}", "viewer.port=0"]
    cfg_of = lambda: load_config([f for f in files if f], [*base, *args.overrides])  # noqa: E731
    from playwright.sync_api import sync_playwright

    runs: list[Run] = []
    renders: list[tuple[str, float, float]] = []
    with sync_playwright() as playwright:
        for n in args.browsers:
            run, worker, dashboard, browser = mapping_run(cfg_of(), n, playwright)
            runs.append(run)
            print(f"{n} browser(s): {run.frames} frames in {run.wall_s:.1f} s", file=sys.stderr)
            if not renders:
                renders = render_times(worker, dashboard)
            if browser is not None:
                browser.close()
            dashboard.stop()
            worker.stop()
    print_tables(runs, renders, " ".join([".venv/bin/python bench/viewer.py", *sys.argv[1:]]))


if __name__ == "__main__":
    main()
