"""Screenshot of the live dashboard for the README: starts `app.py` (the synthetic scene) on a free port, opens
it in headless chromium, waits until the given number of frames is mapped, and saves the page.

    .venv/bin/python scripts/screenshot.py                       # docs/dashboard.png after 120 frames
    .venv/bin/python scripts/screenshot.py --frames 60 --out /tmp/shot.png mapping.optimization.max_iters=5

Needs the test extras (Playwright) and Debian's chromium, as `bash scripts/test.sh` installs them.
"""

from __future__ import annotations

import argparse
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

from playwright.sync_api import Page, sync_playwright

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from h2viz.viewer.chromium import launch_chromium  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def frames_done(page: Page) -> int:
    """Frames mapped so far, as the Mapping panel shows them (0 before it appears)."""
    match = re.search(r"Frames\s+(\d+)\s*/\s*\d+", page.inner_text("body"))
    return int(match.group(1)) if match else 0


def wait_for_url(app: subprocess.Popen[str], timeout_s: float = 120.0) -> str:
    """The dashboard URL that app.py prints once it serves."""
    deadline = time.monotonic() + timeout_s
    assert app.stdout is not None
    while time.monotonic() < deadline:
        line = app.stdout.readline()
        if not line and app.poll() is not None:
            raise SystemExit(f"app.py exited with code {app.returncode} before serving the dashboard")
        if match := re.search(r"(http://\S+)", line):
            return match.group(1)
    raise SystemExit(f"app.py printed no dashboard URL within {timeout_s:.0f} s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=120, help="frames to map before the screenshot")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "dashboard.png")
    parser.add_argument("--size", default="1440x900", help="browser viewport, WIDTHxHEIGHT")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds to wait for the frames")
    parser.add_argument("overrides", nargs="*", help="configuration overrides passed to app.py")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    cmd = [sys.executable, str(ROOT / "app.py"), f"viewer.port={free_port()}", *args.overrides]
    app = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        url = wait_for_url(app)
        with sync_playwright() as playwright:
            browser = launch_chromium(playwright)
            page = browser.new_page(viewport={"width": width, "height": height})
            page.goto(url)
            deadline = time.monotonic() + args.timeout
            while (done := frames_done(page)) < args.frames:
                if time.monotonic() > deadline:
                    raise SystemExit(f"only {done} of {args.frames} frames mapped within {args.timeout:.0f} s")
                page.wait_for_timeout(2000)
            for close in page.locator("button.mantine-Notification-closeButton").all():
                close.click()  # e.g. chromium's "software WebGL" notice
            page.wait_for_timeout(3000)  # the newest mesh chunks and a few frames drawn
            args.out.parent.mkdir(parents=True, exist_ok=True)
            done = frames_done(page)  # mapping went on meanwhile: the frames the picture shows
            page.screenshot(path=str(args.out))
            browser.close()
        print(f"saved {args.out} after {done} frames")
    finally:
        app.terminate()
        app.wait(timeout=30)


if __name__ == "__main__":
    main()
