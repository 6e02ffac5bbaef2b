#!/usr/bin/env bash
# Set up .venv (once; again when pyproject.toml changes) and run the whole test suite: `bash scripts/test.sh [pytest args]`
set -euo pipefail
cd "$(dirname "$0")/.."
# tests/test_netns.py needs `ip` (iproute2), tests/test_security.py `openssl`, tests/test_panel.py
# Debian's `chromium` (driven by Playwright; no browser is downloaded): a bare Debian python image
# has none of them; as root with apt, install them
missing=()
command -v ip >/dev/null || missing+=(iproute2)
command -v openssl >/dev/null || missing+=(openssl)
command -v chromium >/dev/null || missing+=(chromium)
if [ ${#missing[@]} -gt 0 ] && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  # not fatal: without them those tests say what is missing, and the rest of the suite still runs
  # (the browser test fails under CI=true)
  { apt-get update -qq && apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null; } \
    || echo "scripts/test.sh: could not install ${missing[*]} with apt-get" >&2
fi
# .venv with hilsim and its test tools: installed once, again when pyproject.toml changes
source scripts/venv.sh
ensure_venv '.[test]'
.venv/bin/ruff check .
exec .venv/bin/python -m pytest -q "$@"
