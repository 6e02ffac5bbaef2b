#!/usr/bin/env bash
# Set up .venv (if needed) and run the arm scenario headless: `bash scripts/arm.sh [hilsim up options]`
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip >/dev/null
.venv/bin/python -m pip install -q -e .
exec .venv/bin/hilsim up arm "$@"
