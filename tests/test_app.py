"""`python app.py` takes the flags of `h2viz view` and bare section.key=value overrides, and serves the dashboard."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from h2viz.cli import build_config, make_parser

ROOT = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_app_serves_the_dashboard_on_the_port_its_flag_names(tmp_path: Path) -> None:
    port = _free_port()
    cmd = [sys.executable, str(ROOT / "app.py"), "--port", str(port), "--frames", "2", "viewer.start_paused=true",
           "source.synthetic.width=96", "source.synthetic.height=72",
           "mapping.representation.hash_log2_size=14"]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline, lines = time.monotonic() + 120, []
        assert proc.stdout is not None
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if line.startswith("h2viz dashboard:"):
                break
        assert lines and lines[-1].startswith(f"h2viz dashboard: http://127.0.0.1:{port}"), "".join(lines)[-2000:]
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=30) as reply:
            assert reply.status == 200 and b"<html" in reply.read(4096).lower()
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_app_flags_and_bare_overrides_resolve_like_h2viz_view(monkeypatch: pytest.MonkeyPatch) -> None:
    """What app.py hands `h2viz view`: flags as flags, bare overrides as --set before the explicit ones."""
    seen = {}
    monkeypatch.setattr("h2viz.cli._run", lambda args: seen.setdefault("args", args) and 0)
    from h2viz.cli import app_main

    app_main(["--port", "8081", "viewer.render_width=320", "--set", "viewer.render_width=480", "--realtime"])
    args = seen["args"]
    view = make_parser().parse_args(["view", "--port", "8081", "--realtime", "--set", "viewer.render_width=480"])
    assert args.set == ["viewer.render_width=320", "viewer.render_width=480"]
    cfg, expected = build_config(args), build_config(view)
    assert cfg == expected and cfg.viewer.port == 8081 and cfg.viewer.render_width == 480 and cfg.source.realtime
    assert (
        cfg.source.format == "synthetic"
        and cfg.mapping.keyframes.keyframe_iou == expected.mapping.keyframes.keyframe_iou
    )
    with pytest.raises(SystemExit):
        app_main(["--prot", "8081"])
