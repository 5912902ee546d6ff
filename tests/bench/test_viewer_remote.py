"""bench/viewer.py's remote client (a viser client that draws nothing) against a real viser server, and the
per-repetition comparison with headless runs."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bench.viewer import REMOTE_CLIENT, ROOT, Run, Wire, ranges, vs_headless
from h2viz.viewer.server import make_viser_server


@pytest.mark.parametrize("logged", [False, True], ids=["counting", "logging arrivals"])
def test_the_remote_client_counts_as_a_client_and_receives_what_the_scene_sends(logged: bool, tmp_path: Path) -> None:
    server = make_viser_server("127.0.0.1", 0)
    log = tmp_path / "arrivals.tsv"
    reader = subprocess.Popen(
        [sys.executable, "-c", REMOTE_CLIENT, f"ws://127.0.0.1:{server.get_port()}", *([str(log), str(ROOT)] * logged)],
        stdout=subprocess.PIPE,
    )
    try:
        deadline = time.time() + 30
        while not server.get_clients() and time.time() < deadline:
            time.sleep(0.05)
        assert len(server.get_clients()) == 1
        payload = np.random.default_rng(0).bytes(1_000_000)  # incompressible: the wire carries every byte
        server.scene.add_glb("/blob", payload)  # the server forwards it as is; only a browser would parse it
        server.flush()
        time.sleep(1.0)
    finally:
        server.stop()
    out, _ = reader.communicate(timeout=30)
    assert reader.returncode == 0
    assert int(out.decode().strip()) > len(payload)
    assert log.exists() == logged
    if logged:  # the latency run with a remote client: when each mesh chunk arrived, and its size
        wire = Wire()
        wire.read_log(log)
        assert [(name, size) for _, name, size in wire.arrivals] == [("/blob", len(payload))]
        assert 0 < time.time() - wire.arrivals[0][0] < 30 and wire.kinds["GlbMessage"] == [1, len(payload)]


def run(browsers: int, frames: int, seconds: float, repeat: int) -> Run:
    return Run(browsers, frames=frames, mapping_s=seconds, repeat=repeat)


def test_each_run_is_compared_with_the_headless_runs_around_it() -> None:
    runs = [run(-1, 60, 20.0, 0), run(1, 60, 25.0, 0), run(-1, 60, 30.0, 0), run(1, 60, 33.0, 1), run(3, 60, 40.0, 1)]
    headless_speed = (60 / 20.0 + 60 / 30.0) / 2
    assert abs(vs_headless(runs[1], runs) - (60 / 25.0) / headless_speed + 1.0) < 1e-12  # type: ignore[operator]
    assert abs(vs_headless(runs[3], runs) - (30.0 / 33.0 - 1.0)) < 1e-12  # type: ignore[operator]  # only before
    assert abs(vs_headless(runs[4], runs) - (30.0 / 40.0 - 1.0)) < 1e-12  # type: ignore[operator]  # the nearest
    assert vs_headless(runs[0], runs) == 0.0
    assert vs_headless(run(1, 60, 25.0, 2), runs) is None  # not among the runs
    assert vs_headless(runs[1], runs[1:2]) is None  # no headless run at all


def test_late_frames_are_listed_as_ranges() -> None:
    assert ranges([1, 2, 3, 7, 9, 10]) == "1-3, 7, 9-10"
    assert ranges([4]) == "4" and ranges([]) == "-"
