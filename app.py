"""`python app.py`: the live h2viz dashboard, on the built-in synthetic scene unless told otherwise.

Takes the flags of `h2viz view` and bare configuration overrides, e.g.
`python app.py --port 8081 mapping.optimization.max_iters=5` or `python app.py --data path/to/replica/room0`.
"""

from __future__ import annotations

import sys

from h2viz.cli import app_main

if __name__ == "__main__":
    sys.exit(app_main(sys.argv[1:]))
