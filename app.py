"""`python app.py`: the live h2viz dashboard on the built-in synthetic scene at http://127.0.0.1:8080.

Extra arguments are configuration overrides, e.g. `python app.py viewer.port=8081 mapping.max_iters=5`.
"""

from __future__ import annotations

import logging
import sys

from h2viz.config import load_config, source_config_file
from h2viz.viewer.server import run_view


def main(overrides: list[str]) -> None:
    synthetic = source_config_file("synthetic")
    cfg = load_config(
        [synthetic] if synthetic else [], ["source.format=synthetic", "source.path=", *overrides]
    )
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    run_view(cfg, on_ready=lambda url: print(f"h2viz dashboard: {url}  (Ctrl-C to stop)", flush=True))


if __name__ == "__main__":
    main(sys.argv[1:])
