#!/usr/bin/env bash
# Create .venv and install h2viz with its pinned CPU torch build. Idempotent; pass --test to also install
# what the tests need (pytest, Playwright, Debian's chromium).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=.venv/.h2viz-installed
want="$(cat pyproject.toml constraints.txt | sha1sum | cut -c1-12)${1:-}"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  if [ "${1:-}" = "--test" ]; then
    .venv/bin/pip install -q -c constraints.txt -e ".[test]"
  else
    .venv/bin/pip install -q -c constraints.txt -e .
  fi
  echo "$want" > "$stamp"
fi
if [ "${1:-}" = "--test" ] && [ ! -x /usr/bin/chromium ]; then
  SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium >/dev/null
fi
