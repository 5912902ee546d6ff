#!/usr/bin/env bash
# Set up (first run only) and start the live dashboard on the built-in synthetic scene.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/python app.py "$@"
