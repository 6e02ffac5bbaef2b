#!/usr/bin/env bash
# Set up .venv (once; again when pyproject.toml changes) and run the arm scenario headless:
# `bash scripts/arm.sh [hilsim up options]`
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/venv.sh
ensure_venv .
exec .venv/bin/hilsim up arm "$@"
