"""Benchmark of the live dashboard: mapping speed with 0, 1 and 3 connected browsers, latency from a frame
being mapped to its mesh change arriving in a browser, bytes per mesh update, and novel-view render time
per resolution. Browsers are Debian's headless chromium driven by Playwright, on the same machine.

Without a GPU the browsers draw with software WebGL, and chromium runs in a session of its own, which Linux's
autogroup scheduler gives an equal share of the cores: a browser drawing continuously halves mapping speed on
two cores. --browser-background gives the browsers the lowest CPU priority, so that their drawing gets only the
time mapping leaves idle (it still costs mapping some: caches, memory bandwidth). --remote connects clients that
receive everything a browser does and draw nothing: what a browser on another machine, or one drawing with a
GPU, costs this one (meshing, encoding, sending); with --remote-latency the latency run times mesh arrivals at
such a client instead of a local browser. --repeat runs the plan several times with a headless run before
and after every configuration, each compared with the mean of its two neighbours, so that ratios survive the
machine's speed drifting between runs.

    .venv/bin/python bench/viewer.py                      # synthetic scene, configs/fast.yaml, 20 frames
    .venv/bin/python bench/viewer.py --frames 40 mapping.optimization.max_iters=10
    .venv/bin/python bench/viewer.py --config '' mapping.runtime.threads=2     # the default configuration
    .venv/bin/python bench/viewer.py --config '' --browsers 0 1 --browser-background mapping.runtime.threads=2
    .venv/bin/python bench/viewer.py --config '' --frames 60 --browsers 1 --remote 1 --browser-background \
        --no-latency --no-renders --repeat 4 mapping.runtime.threads=2

Speed runs leave the pages alone; the latency run (one browser) ships page 0's websocket frames to this
process to time mesh arrivals, which itself costs CPU, so its speed is shown apart. Latency of frame i: from
the end of its mapping to the browser receiving (first) the first pass and (all) every chunk of the first
mesh job that includes frame i: the chunks whose voxel set changed and those of voxels it allocated, or, for
a frame that allocated nothing, the job's first pass (the chunks of the voxels it observed, most first).
Mapping speed counts frames over the time from the start to the last frame mapped (final meshing and metrics
excluded).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import re
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.realtime import stage_note  # noqa: E402
from h2viz.config import Config, load_config, source_config_file  # noqa: E402
from h2viz.sources.base import FrameSource, make_source  # noqa: E402
from h2viz.types import RgbdFrame  # noqa: E402
from h2viz.viewer.chromium import launch_chromium  # noqa: E402
from h2viz.viewer.server import Dashboard  # noqa: E402
from h2viz.viewer.shapes import view_intrinsics  # noqa: E402
from h2viz.viewer.wire import decode_frame  # noqa: E402
from h2viz.worker import MappingWorker  # noqa: E402

RESOLUTIONS = [(80, 60), (160, 120), (320, 240), (640, 480)]
FRAME_COUNTER = """
window.__h2vizFrames = 0;
for (const proto of [WebGL2RenderingContext.prototype, WebGLRenderingContext.prototype]) {
  const clear = proto.clear;
  proto.clear = function (...args) { window.__h2vizFrames++; return clear.apply(this, args); };
}
"""
"""Counts the scene frames a page draws (three.js clears the canvas once per frame of the viser scene)."""
Key = tuple[int, int, int]
REMOTE_MARK = "h2viz-remote-client"
REMOTE_CLIENT = f"""
import sys, time, msgspec, viser
from viser._messages import ViewerCameraMessage
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect
camera = ViewerCameraMessage((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1.0, 0.01, 100.0, 600, 800, (0.0, 0.0, 1.0),
                             (0.0, -1.0, 0.0))
received = 0  # {REMOTE_MARK}
log = open(sys.argv[2], "w", buffering=1) if len(sys.argv) > 2 else None  # mesh chunk arrivals, one a line
if log is not None:
    sys.path.insert(0, sys.argv[3])
    from h2viz.viewer.wire import decode_frame
try:
    with connect(sys.argv[1], subprotocols=["viser-v" + viser.__version__], max_size=None) as ws:
        ws.send(msgspec.msgpack.encode(camera.as_serializable_dict()))  # viser counts a client from its camera
        for message in ws:
            received += len(message)
            if log is not None and isinstance(message, bytes):
                now = time.time()
                for m in decode_frame(message):
                    log.write(f"{{now}}\\t{{m.type}}\\t{{m.name or ''}}\\t{{m.nbytes}}\\n")
except ConnectionClosed:
    pass
print(received, flush=True)
"""
"""A viser client that receives everything the dashboard sends and draws nothing: a browser on another machine
(or with a GPU), as far as this machine's CPU is concerned. It runs in a process of its own, counted apart, and
prints the bytes it received when the server closes the connection. Given a file and the project root, it also
writes each message it receives there (time, type, name, bytes: the latency run with a remote client)."""


@dataclass
class Run:
    """What one mapping run with `browsers` connected pages measured."""

    browsers: int
    recorded: bool = False  # page 0's websocket frames were recorded (the latency run)
    background: bool = False  # the browsers ran at the lowest CPU priority
    remote: bool = False  # plain websocket readers instead of browsers (what a browser elsewhere costs)
    repeat: int = 0  # which repetition of the plan this run belongs to (--repeat)
    frames: int = 0
    mapping_s: float = 0.0  # start -> last frame mapped
    map_s: list[float] = field(default_factory=list)  # Mapper.integrate per frame
    first_s: list[float] = field(default_factory=list)  # frame mapped -> first pass of its job in the browser
    all_s: list[float] = field(default_factory=list)  # frame mapped -> all its job's required chunks there
    submit_s: list[float] = field(default_factory=list)  # frame mapped -> the job that includes it submitted
    start_s: list[float] = field(default_factory=list)  # frame mapped -> that job started
    extract_s: list[float] = field(default_factory=list)  # frame mapped -> that job's chunks for it extracted
    published_s: list[float] = field(default_factory=list)  # frame mapped -> the mesh thread published them
    sent_s: list[float] = field(default_factory=list)  # frame mapped -> the dashboard sent all of them
    waited_s: list[float] = field(default_factory=list)  # real-time: frame arrived -> integrated
    unchanged: int = 0  # frames whose mesh job had no chunk to re-mesh at once (nothing to time)
    arrived_all_s: list[float] = field(default_factory=list)  # real-time: frame arrived -> all its chunks there
    job_s: list[float] = field(default_factory=list)  # job submitted -> its required passes done
    job_chunks: list[int] = field(default_factory=list)  # required chunks per job
    refreshed: int = 0  # chunks re-meshed by refresh passes
    mesh_busy_share: float = 0.0  # mesh thread busy time / mapping time
    update_bytes: list[int] = field(default_factory=list)  # GLB payload per mesh update received
    update_chunks: list[int] = field(default_factory=list)
    whole_mesh_bytes: int = 0
    cpu_s: dict[str, float] = field(default_factory=dict)  # CPU seconds while mapping, by thread / process
    cpu_window_s: float = 0.0  # the seconds cpu_s covers (0: mapping_s)
    messages: dict[str, tuple[int, int]] = field(default_factory=dict)  # browser 0: type -> (count, bytes)
    ws_frames: int = 0  # websocket frames browser 0 received
    gl_frames: int = 0  # scene frames page 0 drew while mapping

    @property
    def label(self) -> str:
        if self.browsers < 0:
            return "headless (no dashboard, no meshing)"
        if self.browsers == 0:
            return "0 browser(s) (dashboard up, nothing meshed until a browser connects)"
        if self.remote:
            recorded = ", recording its websocket" if self.recorded else ""
            return f"{self.browsers} remote client(s) (drawing elsewhere){recorded}"
        label = f"{self.browsers} browser(s)" + (" at background priority" if self.background else "")
        return label + (", recording page 0's websocket" if self.recorded else "")


def cpu_seconds() -> dict[str, float]:
    """CPU seconds so far of this process's threads (by name) and of its child processes (the browsers)."""
    tick = os.sysconf("SC_CLK_TCK")
    names = {t.native_id: t.name if t.name.startswith("h2viz-") else "other Python threads (viser, ...)"
             for t in threading.enumerate()}  # fmt: skip
    out: dict[str, float] = {}
    for task in Path("/proc/self/task").iterdir():
        try:
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        key = names.get(int(task.name), "native threads (torch and numba workers)")
        out[key] = out.get(key, 0.0) + (int(fields[11]) + int(fields[12])) / tick
    for kind, ticks in _tree_ticks(os.getpid()).items():
        out[kind] = ticks / tick
    return out


def _process_kind(pid: int) -> str:
    """What a descendant process is: a chromium renderer / GPU / other process, or Playwright's driver."""
    try:
        cmdline = (Path("/proc") / str(pid) / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return "browser: other"
    if REMOTE_MARK in cmdline:
        return "remote client (websocket reader)"
    if "chrom" not in cmdline.split(" ", 1)[0]:
        return "playwright driver (test harness)"
    kind = re.search(r"--type=(\S+)", cmdline)  # chromium rewrites its children's argv into one string
    return f"browser: {kind.group(1) if kind else 'main'}"


def background_browsers(root: int) -> None:
    """Give every chromium process under `root` the lowest CPU priority. Chromium runs in a session of its own,
    which Linux's autogroup scheduling treats as a peer of this process's session (an equal share of the cores
    whatever the threads' nice values, which chromium sets itself anyway): the session's autogroup goes to
    nice 19 and every thread to SCHED_IDLE."""
    for pid in _descendants(root, _processes()):
        if not _process_kind(pid).startswith("browser:"):
            continue
        with contextlib.suppress(OSError):  # no autogroup scheduling in this kernel, or the process ended
            Path(f"/proc/{pid}/autogroup").write_text("19")
        for task in Path(f"/proc/{pid}/task").glob("*"):
            with contextlib.suppress(OSError):  # the thread ended meanwhile
                os.sched_setscheduler(int(task.name), os.SCHED_IDLE, os.sched_param(0))


def _processes() -> dict[int, tuple[int, int]]:
    """pid -> (parent pid, utime + stime including that of reaped children), over every process."""
    out: dict[int, tuple[int, int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out[int(entry.name)] = (int(fields[1]), int(fields[11]) + int(fields[12]) + int(fields[13]) + int(fields[14]))
    return out


def _descendants(root: int, processes: dict[int, tuple[int, int]]) -> list[int]:
    """Every descendant pid of `root` among `processes`."""
    children: dict[int, list[int]] = {}
    for pid, (ppid, _) in processes.items():
        children.setdefault(ppid, []).append(pid)
    out, todo = [], list(children.get(root, []))
    while todo:
        pid = todo.pop()
        out.append(pid)
        todo += children.get(pid, [])
    return out


def _tree_ticks(root: int) -> dict[str, int]:
    """utime + stime (and that of reaped children) of every descendant process of `root`, by process kind."""
    processes = _processes()
    out: dict[str, int] = {}
    for pid in _descendants(root, processes):
        kind = _process_kind(pid)
        out[kind] = out.get(kind, 0) + processes[pid][1]
    return out


@dataclass
class Wire:
    """Mesh sends of the dashboard and GLB arrivals in page 0."""

    sends: list[tuple[float, dict[Key, int]]] = field(default_factory=list)  # (time, {chunk: version})
    shown: list[tuple[float, int, frozenset[Key]]] = field(default_factory=list)  # (time, newest version, chunks)
    arrivals: list[tuple[float, str, int]] = field(default_factory=list)  # (time, node name, bytes)
    kinds: dict[str, list[int]] = field(default_factory=dict)  # message type -> [count, bytes]
    frames: int = 0  # websocket frames received

    def on_sent(self, snap: Any, keys: list[Key], nbytes: int) -> None:
        now, newest = time.time(), max((c.version for c in snap.chunks.values()), default=-1)
        self.shown.append((now, newest, frozenset(snap.chunks)))
        if keys:
            self.sends.append((now, {k: snap.chunks[k].version for k in keys if k in snap.chunks}))

    def on_frame(self, payload: Any) -> None:
        now = time.time()
        if isinstance(payload, bytes):
            messages = decode_frame(payload)
            self.frames += 1
            for m in messages:
                count = self.kinds.setdefault(m.type, [0, 0])
                count[0], count[1] = count[0] + 1, count[1] + m.nbytes
            self.arrivals.extend((now, m.name, m.nbytes) for m in messages if m.type == "GlbMessage" and m.name)

    def read_log(self, path: Path) -> None:
        """Take the messages a remote client wrote to `path` (REMOTE_CLIENT) as this wire's arrivals."""
        frames: set[str] = set()
        for line in path.read_text().splitlines():
            t, kind, name, nbytes = line.split("\t")
            frames.add(t)
            count = self.kinds.setdefault(kind, [0, 0])
            count[0], count[1] = count[0] + 1, count[1] + int(nbytes)
            if kind == "GlbMessage" and name:
                self.arrivals.append((float(t), name, int(nbytes)))
        self.frames += len(frames)

    def sent(self, key: Key, version: int) -> float | None:
        """When the dashboard first sent chunk `key` at `version` (or newer), or dropped it from the scene."""
        first = self._sent_or_dropped(key, version)
        return None if first is None else first[0]

    def arrival(self, key: Key, version: int) -> tuple[float, int] | None:
        """(time, bytes) the browser first received chunk `key` at `version` (or a newer one); for a chunk
        meshed empty (the mesher drops it) there is nothing to receive: the time the scene was updated without it."""
        first = self._sent_or_dropped(key, version)
        if first is None:
            return None
        t_sent, dropped = first
        if dropped:
            return t_sent, 0  # meshed empty: the scene dropped the chunk (or never had it), nothing to receive
        name = node_name(key)
        return next(((t, b) for t, n, b in self.arrivals if n == name and t >= t_sent - 0.01), None)

    def _sent_or_dropped(self, key: Key, version: int) -> tuple[float, bool] | None:
        """(time, dropped): the dashboard's first send of chunk `key` at `version` or newer, or (dropped) the
        scene update without it when that came first; None when neither happened."""
        sent = next((t for t, chunks in self.sends if chunks.get(key, -1) >= version), None)
        gone = next((t for t, newest, keys in self.shown if newest >= version and key not in keys), None)
        if gone is not None and (sent is None or gone < sent):
            return gone, True
        return None if sent is None else (sent, False)


def node_name(key: Key) -> str:
    return "/mesh/c_" + "_".join(str(int(k)).replace("-", "m") for k in key)


class Preloaded(FrameSource):
    """Frames read before the run, so that no run pays for loading them (--read-frames: read as the app does);
    read once per source configuration and shared by the runs of one benchmark."""

    format_name = "preloaded"
    _read: dict[str, tuple[list[RgbdFrame], Any]] = {}

    def __init__(self, cfg: Config) -> None:
        super().__init__(dataclasses.replace(cfg.source, stride=1, max_frames=0, downscale=1))
        key = repr(cfg.source)
        if key not in Preloaded._read:
            source = make_source(cfg.source)
            Preloaded._read[key] = (list(source), source.ground_truth_mesh())
        self.frames, self.gt = Preloaded._read[key]

    def keys(self) -> list[int]:
        return list(range(len(self.frames)))

    def load(self, position: int, key: Any) -> RgbdFrame:
        return self.frames[int(key)]

    def ground_truth_mesh(self) -> Any:
        return self.gt


def headless_run(cfg: Config) -> Run:
    """Mapper.integrate over the same frames, without worker, meshing or dashboard (browsers = -1)."""
    from h2viz.mapping.mapper import Mapper

    frames = Preloaded(cfg).frames
    Mapper(cfg.mapping).integrate(frames[0])  # warm-up: compiled kernels load, thread pools start
    run, mapper = Run(-1), Mapper(cfg.mapping)
    t0, cpu0 = time.time(), cpu_seconds()
    for frame in frames:
        run.map_s.append(mapper.integrate(frame).map_time_s)
    run.mapping_s, run.frames = time.time() - t0, len(run.map_s)
    run.cpu_s = {k: v - cpu0.get(k, 0.0) for k, v in cpu_seconds().items()}
    return run


def mapping_run(
    cfg: Config,
    n_browsers: int,
    playwright: Any,
    hide_mesh: bool = False,
    record: bool = False,
    background: bool = False,
    remote: bool = False,
    autosave_dir: Path | None = None,
    read_frames: bool = False,
) -> tuple[Run, MappingWorker, Dashboard, Any]:
    """Map with the dashboard and `n_browsers` pages open. With `record`, page 0's websocket frames are
    shipped to this process and decoded to time mesh arrivals: that costs both cores real CPU, so speed is
    measured in runs without it. `background` gives the browsers the lowest CPU priority (see --browser-background);
    `remote` connects `n_browsers` REMOTE_CLIENT processes instead of browsers; `autosave_dir`: autosaves go there,
    as the app's go to its run folder (None: none); `read_frames`: the source reads each frame as the app's does (the
    synthetic room from its frame cache) instead of taking it from memory."""
    from h2viz.mapping.mapper import Mapper

    run, wire = Run(n_browsers, recorded=record, background=background, remote=remote), Wire()
    source: FrameSource
    if read_frames:
        source = make_source(cfg.source)
    else:
        source = Preloaded(cfg)
        cfg = dataclasses.replace(cfg, source=source.cfg)  # every preloaded frame, in order
    worker = MappingWorker(source, Mapper(cfg.mapping), cfg, autosave_dir=autosave_dir)
    dashboard = Dashboard(worker, cfg, port=0)
    dashboard.layers.mesh.set_enabled(not hide_mesh)
    dashboard.layers.mesh.on_sent.append(wire.on_sent)
    browser = None
    pages: list[Any] = []
    readers: list[subprocess.Popen[bytes]] = []
    if n_browsers and not remote:
        browser = launch_chromium(playwright)
        pages = [browser.new_page(viewport={"width": 800, "height": 600}) for _ in range(n_browsers)]
        for page in pages:
            page.add_init_script(FRAME_COUNTER)
        if record:
            pages[0].on("websocket", lambda ws: ws.on("framereceived", wire.on_frame))
    dashboard.start()
    for page in pages:
        page.goto(dashboard.url)
    log = Path(tempfile.mkdtemp(prefix="h2viz-bench-")) / "arrivals.tsv" if remote and record else None
    if remote:
        ws_url = dashboard.url.replace("http://", "ws://")
        logged = [] if log is None else [str(log), str(ROOT)]
        readers = [
            subprocess.Popen([sys.executable, "-c", REMOTE_CLIENT, ws_url, *(logged if i == 0 else [])])
            for i in range(n_browsers)
        ]
    deadline = time.time() + 120
    while dashboard.client_count() < n_browsers and time.time() < deadline:
        time.sleep(0.2)
    if dashboard.client_count() < n_browsers:
        raise SystemExit(f"only {dashboard.client_count()} of {n_browsers} clients connected within 120 s")
    drawn = lambda: int(pages[0].evaluate("window.__h2vizFrames || 0")) if pages else 0  # noqa: E731
    t0, cpu0, frames0 = time.time(), cpu_seconds(), drawn()
    worker.start()
    next_check = 0.0
    first: tuple[float, dict[str, float]] | None = None  # time and CPU seconds when the first frame was mapped
    last, n_last = (t0, cpu0), 0  # ... when the latest count was read (at most a second after it changed)
    while len(worker.mapped_at) < len(source) and not worker.wait_finished(0.05):
        if background and time.time() > next_check:  # and the threads the browsers started since
            background_browsers(os.getpid())
            next_check = time.time() + 1.0
        if record and pages:
            pages[0].wait_for_timeout(100)  # Playwright delivers the frame events while it waits
        if len(worker.mapped_at) != n_last and (first is None or time.time() - last[0] >= 1.0):
            last, n_last = (time.time(), cpu_seconds()), len(worker.mapped_at)  # at most once a second: /proc
            first = first or last  # reads hold the GIL, which the mapping thread waits for
    cpu1 = cpu_seconds()
    run.cpu_s = {k: v - cpu0.get(k, 0.0) for k, v in cpu1.items()}
    if first is not None and last[0] - first[0] > 1.0:  # the CPU from the first frame mapped to the last
        run.cpu_window_s = last[0] - first[0]
        run.cpu_s = {k: v - first[1].get(k, 0.0) for k, v in last[1].items()}
    run.gl_frames = drawn() - frames0
    while not worker.wait_finished(0.05):
        if pages:
            pages[0].wait_for_timeout(100)
    if pages:
        pages[0].wait_for_timeout(3000)  # let the last update arrive
    elif log is not None:
        time.sleep(3.0)
    for reader in readers:
        reader.terminate()
        reader.wait(10)
    if log is not None:
        wire.read_log(log)
        shutil.rmtree(log.parent, ignore_errors=True)
    snap = worker.slot.get()[1]
    run.frames = snap.frames_done
    run.map_s = [s.map_time_s for s in snap.stats]
    run.mapping_s = max(worker.mapped_at.values()) - t0
    _measure(run, worker, wire)
    run.messages = {k: (c, b) for k, (c, b) in wire.kinds.items()}
    run.ws_frames = wire.frames
    from h2viz.viewer.glb import mesh_glb

    run.whole_mesh_bytes = sum(len(mesh_glb(c.vertices, c.faces, c.colors)) for c in snap.chunks.values())
    return run, worker, dashboard, browser


def _measure(run: Run, worker: MappingWorker, wire: Wire) -> None:
    """Latencies per frame, job durations and bytes per update from the pass log and the wire."""
    passes = list(worker.meshing.passes)
    published_at = list(worker.meshing.published)  # copies: the mesh thread may still be publishing
    jobs: dict[int, list[Any]] = {}
    for p in passes:
        jobs.setdefault(p.job_version, []).append(p)
    required = {v: [p for p in ps if p.required] for v, ps in jobs.items()}
    for ps in required.values():
        if ps:
            run.job_s.append(ps[-1].finished - ps[0].submitted)
            run.job_chunks.append(sum(len(p.chunks) for p in ps))
    run.refreshed = sum(len(p.chunks) for p in passes if not p.required)
    run.mesh_busy_share = worker.meshing.busy_s / max(run.mapping_s, 1e-9)
    arrived = worker._feed.arrived_at  # real-time mode: when each frame joined the backlog
    ran = sorted(worker.meshing.jobs, key=lambda j: j.version)  # every job run, those that re-meshed nothing too
    versions = sorted(jobs)  # the jobs that ran a pass
    for n, (index, t_mapped) in enumerate(sorted(worker.mapped_at.items(), key=lambda item: item[1]), start=1):
        if index in arrived:
            run.waited_s.append(t_mapped - arrived[index])
        first_job = next((j for j in ran if j.field_version >= n), None)
        if first_job is not None and first_job.passes == 0 and not first_job.cut_short:
            run.unchanged += 1  # its job had no chunk to re-mesh (no new voxel; refresh passes show it later)
            continue
        version = next((v for v in versions if jobs[v][0].field_version >= n), None)
        if version is None:
            continue
        # the frame's chunks: its job's required ones, or when it allocated nothing (no voxel set changed) the
        # first pass over the voxels it observed (those chunks come first, most observed voxels first)
        own = required[version] or jobs[version][:1]
        first = [wire.arrival(k, version) for k in own[0].chunks]
        every = [wire.arrival(k, version) for p in own for k in p.chunks]
        if any(first):
            run.first_s.append(min(a[0] for a in first if a) - t_mapped)
        if every and all(every):
            run.all_s.append(max(a[0] for a in every if a) - t_mapped)
            if index in arrived:
                run.arrived_all_s.append(max(a[0] for a in every if a) - arrived[index])
            sent = [wire.sent(k, version) for p in own for k in p.chunks]
            run.submit_s.append(own[0].submitted - t_mapped)
            run.start_s.append(own[0].started - t_mapped)
            extracted = max(p.finished for p in own)
            run.extract_s.append(extracted - t_mapped)
            published = next((t for t in published_at if t >= extracted), None)
            if published is not None:
                run.published_s.append(published - t_mapped)
            if all(t is not None for t in sent):
                run.sent_s.append(max(t for t in sent if t is not None) - t_mapped)
    for t_sent, chunks in wire.sends:
        got = [a for k, v in chunks.items() if (a := wire.arrival(k, v)) is not None and a[0] >= t_sent - 0.01]
        if got:
            run.update_bytes.append(sum(b for _, b in got))
            run.update_chunks.append(len(chunks))


def render_times(worker: MappingWorker) -> list[tuple[str, float, float]]:
    """(resolution, rgb render s, background render s = rgb + half-resolution depth) at the last pose."""
    frame = worker.slot.get()[1].current_frame
    out = []
    for width, height in RESOLUTIONS:
        K = view_intrinsics(2 * np.arctan2(0.5 * frame.height, frame.K[1, 1]), width, height)
        args = {"K": K, "T_world_camera": frame.T_world_camera, "height": height, "width": width}
        rgb = worker.submit("render", mode="rgb", **args).result(600).seconds
        both = worker.submit("render", mode="rgb", with_depth=True, depth_downscale=2, **args).result(600).seconds
        out.append((f"{width}x{height}", rgb, both))
    return out


def ranges(positions: list[int]) -> str:
    """Sorted positions as ranges: [1, 2, 3, 7, 9, 10] -> "1-3, 7, 9-10"."""
    runs: list[list[int]] = []
    for p in positions:
        if runs and p == runs[-1][1] + 1:
            runs[-1][1] = p
        else:
            runs.append([p, p])
    return ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs) or "-"


def _median_p90_max(values: list[float], scale: float = 1.0) -> str:
    if not values:
        return "-"
    p90 = statistics.quantiles(values, n=10, method="inclusive")[-1] if len(values) > 1 else values[0]
    return f"{scale * statistics.median(values):.0f} / {scale * p90:.0f} / {scale * max(values):.0f}"


def vs_headless(run: Run, runs: list[Run]) -> float | None:
    """Relative mapping speed of `run` against the nearest headless runs before and after it in `runs` (listed in
    the order they ran): their mean speed, or the one there is. None when `run` is not in `runs` or has neither."""
    i = next((i for i, r in enumerate(runs) if r is run), None)
    if i is None:
        return None
    if run.browsers < 0:
        return 0.0
    before = next((r for r in reversed(runs[:i]) if r.browsers < 0), None)
    after = next((r for r in runs[i + 1 :] if r.browsers < 0), None)
    speeds = [r.frames / r.mapping_s for r in (before, after) if r is not None]
    if not speeds:
        return None
    return (run.frames / run.mapping_s) / statistics.fmean(speeds) - 1.0


def print_repeats(runs: list[Run]) -> None:
    """With --repeat: each configuration's speed against the headless runs around it, per repetition."""
    if len({r.repeat for r in runs}) < 2:
        return
    by_label: dict[str, list[float]] = {}
    for r in runs:
        rel = vs_headless(r, runs)
        if r.browsers >= 0 and rel is not None:
            by_label.setdefault(r.label, []).append(rel)
    print("\n| vs the headless runs just before and after | each repetition | median |\n|---|---|---:|")
    for label, rels in by_label.items():
        each = ", ".join(f"{100 * v:+.0f} %" for v in rels)
        print(f"| {label} | {each} | {100 * statistics.median(rels):+.0f} % |")


def print_tables(runs: list[Run], renders: list[tuple[str, float, float]], command: str) -> None:
    print(f"\nReproduce: {command}\n")
    print("| browsers | frames | mapping s | frames / s | vs headless | mapper s / frame (median) |")
    print("|---|---:|---:|---:|---:|---:|")
    for r in runs:
        rate, median, rel = r.frames / r.mapping_s, statistics.median(r.map_s), vs_headless(r, runs)
        shown = f"{100 * rel:+.0f} %" if rel is not None else "-"
        print(f"| {r.label} | {r.frames} | {r.mapping_s:.1f} | {rate:.3f} | {shown} | {median:.2f} |")
    print_repeats(runs)
    for r in runs:
        if not r.recorded:
            continue
        rows = [
            (f"frame mapped -> first mesh change in the browser, ms ({len(r.first_s)} frames)", r.first_s, 1000),
            (f"frame mapped -> all of its chunks in the browser, ms ({len(r.all_s)} frames)", r.all_s, 1000),
            ("  of which: frame mapped -> the job that includes it submitted, ms", r.submit_s, 1000),
            ("  frame mapped -> that job started (the one before it ended), ms", r.start_s, 1000),
            ("  frame mapped -> that job's chunks for it extracted, ms", r.extract_s, 1000),
            ("  frame mapped -> the mesh thread published them, ms", r.published_s, 1000),
            ("  frame mapped -> the dashboard sent them all, ms", r.sent_s, 1000),
            ("real-time: frame arrived -> integrated (its wait in the backlog), ms", r.waited_s, 1000),
            (
                f"real-time: frame arrived -> all of its chunks in the browser, ms ({len(r.arrived_all_s)} frames)",
                r.arrived_all_s,
                1000,
            ),
            ("mesh job submitted -> its required chunks extracted, ms", r.job_s, 1000),
            ("required chunks per job", [float(c) for c in r.job_chunks], 1),
            ("kB per mesh update received", [float(b) for b in r.update_bytes], 1e-3),
            ("chunks per mesh update", [float(c) for c in r.update_chunks], 1),
        ]
        print(f"\n| mesh streaming ({r.label}) | median / p90 / max |\n|---|---:|")
        for name, values, scale in rows:
            print(f"| {name} | {_median_p90_max(values, scale)} |")
        late = [n for n, s in enumerate(r.all_s, start=1) if s > 1.0]
        print(f"| frames whose chunks took more than 1 s to reach the browser | {len(late)} of {len(r.all_s)} |")
        print(f"| those frames (their places in integration order, among the frames timed) | {ranges(late)} |")
        if r.arrived_all_s:
            late = [s for s in r.arrived_all_s if s > 1.0]
            print(
                f"| real-time: frames whose chunks reached the browser more than 1 s after the frame arrived | "
                f"{len(late)} of {len(r.arrived_all_s)} |"
            )
        print(
            "| frames left out above: their mesh job had no chunk to re-mesh at once (no new voxel; later refresh "
            f"passes show what they changed) | {r.unchanged} |"
        )
        print(f"| mesh updates received | {len(r.update_bytes)} |")
        print(f"| chunks re-meshed by refresh passes | {r.refreshed} |")
        print(f"| mesh thread busy / mapping time | {100 * r.mesh_busy_share:.0f} % |")
        print(f"| whole final mesh as GLB chunks, kB | {r.whole_mesh_bytes / 1e3:.0f} |")
        top = sorted(r.messages.items(), key=lambda kv: -kv[1][0])[:6]
        print(f"| websocket frames received / s | {r.ws_frames / r.mapping_s:.1f} |")
        print("| messages received (count, kB) | " + ", ".join(f"{k} {c} ({b / 1e3:.0f})" for k, (c, b) in top) + " |")
    heads = " | ".join(r.label for r in runs)
    print(f"\n| CPU while frames were integrated (read once a second), % of one core | {heads} |")
    print("|---|" + "---:|" * len(runs))
    for name in sorted({k for r in runs for k in r.cpu_s}):
        cells = " | ".join(f"{100 * r.cpu_s.get(name, 0.0) / (r.cpu_window_s or r.mapping_s):.0f}" for r in runs)
        print(f"| {name} | {cells} |")
    shown = [r for r in runs if r.browsers > 0 and not r.remote]
    if shown:
        print(f"\n| page 0 (800x600, software WebGL) | {' | '.join(r.label for r in shown)} |")
        print("|---|" + "---:|" * len(shown))
        print("| scene frames drawn / s | " + " | ".join(f"{r.gl_frames / r.mapping_s:.1f}" for r in shown) + " |")
        per_frame = []
        for r in shown:  # every browser's CPU over every page's frames (pages draw alike)
            browser_s = sum(v for k, v in r.cpu_s.items() if k.startswith("browser:"))
            per_frame.append(f"{1000 * browser_s / max(1, r.gl_frames * r.browsers):.0f}")
        print("| browser CPU ms / frame | " + " | ".join(per_frame) + " |")
    print("\n| novel view | rgb render ms | background (rgb + half-res depth) ms |\n|---|---:|---:|")
    for res, rgb, both in renders:
        print(f"| {res} | {1000 * rgb:.0f} | {1000 * both:.0f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=20, help="frames mapped per run")
    parser.add_argument("--browsers", type=int, nargs="*", default=[0, 1, 3], help="browser counts to run")
    parser.add_argument(
        "--remote",
        type=int,
        nargs="*",
        default=[],
        help="also run with this many remote clients: processes that receive everything a browser does and draw "
        "nothing, as a browser on another machine (or with a GPU) would cost this one",
    )
    parser.add_argument(
        "--repeat",
        type=int,
        default=1,
        help="run the whole plan this often, with a headless run before and after every configuration",
    )
    parser.add_argument("--no-renders", action="store_true", help="skip the novel-view render timings")
    parser.add_argument("--no-headless", action="store_true", help="skip the run without dashboard")
    parser.add_argument("--no-latency", action="store_true", help="skip the run that times mesh arrivals")
    parser.add_argument(
        "--remote-latency",
        action="store_true",
        help="time mesh arrivals at a remote client (a browser drawing elsewhere) instead of a local browser",
    )
    parser.add_argument("--hide-mesh", action="store_true", help="mesh layer off (what the rest of the page costs)")
    parser.add_argument(
        "--browser-background",
        action="store_true",
        help="run the browsers at the lowest CPU priority: their software WebGL drawing then uses only the CPU "
        "time mapping leaves idle",
    )
    parser.add_argument(
        "--autosave",
        action="store_true",
        help="autosave (autosave.*) into a temporary folder, as the app does into its run folder",
    )
    parser.add_argument(
        "--read-frames",
        action="store_true",
        help="the source reads each frame as the app's does (the synthetic room from its frame cache, rendering the "
        "frames not cached before a real-time stream starts) instead of taking it from memory",
    )
    parser.add_argument(
        "--config", default=str(ROOT / "configs" / "fast.yaml"), help="config file over the defaults ('' = none)"
    )
    parser.add_argument("overrides", nargs="*", help="config overrides, e.g. mapping.optimization.max_iters=5")
    args = parser.parse_args()
    files = [source_config_file("synthetic"), Path(args.config) if args.config else None]
    base = ["source.format=synthetic", "source.stride=4", f"source.max_frames={args.frames}", "viewer.port=0"]
    cfg_of = lambda: load_config([f for f in files if f], [*base, *args.overrides])  # noqa: E731
    from playwright.sync_api import sync_playwright

    runs: list[Run] = []
    renders: list[tuple[str, float, float]] = []
    plan = [(n, False, False) for n in args.browsers] + [(n, False, True) for n in args.remote]
    plan += [] if args.no_latency else [(1, True, args.remote_latency)]
    with sync_playwright() as playwright:
        for repeat in range(args.repeat):
            steps: list[tuple[int, bool, bool] | None] = [None, *plan]
            if args.repeat > 1:  # each configuration between two headless runs, in reversed order every other
                # time: the machine's speed drifts by up to a third within an hour, less between neighbouring runs
                order = plan if repeat % 2 == 0 else plan[::-1]
                steps = [None] if repeat == 0 else []
                for step in order:
                    steps += [step, None]
            for step in steps:
                if step is None:
                    if not args.no_headless:
                        runs.append(dataclasses.replace(headless_run(cfg_of()), repeat=repeat))
                    continue
                n, record, remote = step
                folder = Path(tempfile.mkdtemp(prefix="h2viz-bench-")) if args.autosave else None
                run, worker, dashboard, browser = mapping_run(
                    cfg_of(), n, playwright, args.hide_mesh, record, args.browser_background, remote, folder,
                    args.read_frames,
                )
                run.repeat = repeat
                runs.append(run)
                feed = worker._feed  # real-time mode: frames the stream delivered that were not integrated
                dropped = f" ({feed.passed_over} read too late, {feed.overflowed} beyond the backlog)"
                mapped = {s.index for s in worker.slot.get()[1].stats}
                source = worker.source
                played = (
                    [f.index for f in source.frames]
                    if isinstance(source, Preloaded)
                    else [int(k) for _, k in source.selected()]  # type: ignore[call-overload]
                )
                if mapped and len(mapped) < len(played):
                    dropped += f"; not integrated: frames {ranges([i for i in played if i not in mapped])}"
                print(f"{run.label}: {run.frames} frames mapped in {run.mapping_s:.1f} s{dropped}", file=sys.stderr)
                print(f"{run.label}: {stage_note(worker.slot.get()[1].stats)}", file=sys.stderr)
                if not renders and not args.no_renders:
                    renders = render_times(worker)
                if browser is not None:
                    browser.close()
                dashboard.stop()
                worker.stop()
                if folder is not None:
                    saves = worker._autosave.saves if worker._autosave is not None else 0
                    print(f"{run.label}: {saves} autosaves", file=sys.stderr)
                    shutil.rmtree(folder, ignore_errors=True)
    print_tables(runs, renders, shlex.join([".venv/bin/python", "bench/viewer.py", *sys.argv[1:]]))


if __name__ == "__main__":
    main()
