#!/usr/bin/env bash
# Set up .venv (if needed) and run the whole test suite: `bash scripts/test.sh [pytest args]`
set -euo pipefail
cd "$(dirname "$0")/.."
# tests/test_netns.py needs `ip` (iproute2), tests/test_security.py `openssl`: a bare Debian
# python image has neither; as root with apt, install them
if { ! command -v ip >/dev/null || ! command -v openssl >/dev/null; } && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  # not fatal: without them those tests say what is missing, and the rest of the suite still runs
  { apt-get update -qq && apt-get install -y -qq --no-install-recommends iproute2 openssl >/dev/null; } \
    || echo "scripts/test.sh: could not install iproute2/openssl with apt-get" >&2
fi
if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip >/dev/null
.venv/bin/python -m pip install -q -e '.[test]'
.venv/bin/ruff check .
exec .venv/bin/python -m pytest -q "$@"
