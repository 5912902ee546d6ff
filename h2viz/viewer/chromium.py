"""How h2viz's tests, benchmarks and screenshot script start Debian's chromium headless: the executable and
flags that keep it from opening connections of its own (this machine's network refuses them, many at a time)
and let it run as root in a container."""

from __future__ import annotations

from pathlib import Path
from typing import Any

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
    "--disable-sync",
]


def launch_chromium(playwright: Any) -> Any:
    """A headless chromium Browser from Playwright's sync API (the caller's `sync_playwright()` object)."""
    return playwright.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS, headless=True)
