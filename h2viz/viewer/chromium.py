"""How h2viz's tests, benchmarks and screenshot script start Debian's chromium headless: the executable and
flags that keep it from opening connections of its own (this machine's network refuses them, many at a time)
and let it run as root in a container."""

from __future__ import annotations

from pathlib import Path

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
    "--disable-sync",
]
