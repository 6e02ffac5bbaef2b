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
# Rerun's headless viewer (tests/test_live.py, tests/test_bench.py: `hilsim bench loop --live`) draws with
# Vulkan, by software here: Mesa's lavapipe (with OpenGL alone it stops at its first frame)
ls /usr/share/vulkan/icd.d/lvp_icd.*.json >/dev/null 2>&1 || missing+=(mesa-vulkan-drivers)
# tests/test_compose_run.py runs docker/compose.yaml in containers with Podman: podman and runc (crun
# refuses this machine's mixed cgroups), catatonit (`init: true`), netavark, aardvark-dns and
# iptables (the compose network, its names, the published port), mmdebstrap (the base image, built
# from the apt mirror: no registry is reachable)
command -v podman >/dev/null || missing+=(podman)
command -v runc >/dev/null || missing+=(runc)
command -v mmdebstrap >/dev/null || missing+=(mmdebstrap)
command -v iptables >/dev/null || missing+=(iptables)
[ -x /usr/libexec/podman/catatonit ] || missing+=(catatonit)
[ -x /usr/lib/podman/netavark ] || missing+=(netavark)
[ -x /usr/lib/podman/aardvark-dns ] || missing+=(aardvark-dns)
if [ ${#missing[@]} -gt 0 ] && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  # not fatal: without them those tests say what is missing, and the rest of the suite still runs
  # (the browser test fails under CI=true)
  { apt-get update -qq && apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null; } \
    || echo "scripts/test.sh: could not install ${missing[*]} with apt-get" >&2
fi
# .venv with hilsim and its test tools: installed once, again when pyproject.toml changes
source scripts/venv.sh
ensure_venv '.[test]'
# podman-compose for tests/test_compose_run.py, from PyPI: Debian 12's (1.0.3) ignores profiles and
# would start every HIL bridge; then the base image, built only when missing (podman keeps it, and
# the test's image and wheels, between runs on this machine)
if [ ! -x .venv/bin/podman-compose ]; then
  .venv/bin/python -m pip install -q 'podman-compose>=1.1' \
    || echo "scripts/test.sh: could not install podman-compose with pip" >&2
fi
if command -v podman >/dev/null && command -v mmdebstrap >/dev/null; then
  CONTAINERS_CONF="${CONTAINERS_CONF:-$PWD/config/podman/containers.conf}" bash docker/build-offline.sh --base-only \
    || echo "scripts/test.sh: could not build the base image (docker/build-offline.sh --base-only)" >&2
fi
# real ROS 2 (Kilted and Jazzy rclpy wheels) for tests/test_ros2_real.py, in venvs of their own, installed
# beside the suite (mostly downloads); the tests that need them wait for them
mkdir -p .venv-ros2
setsid bash scripts/ros2-venvs.sh > .venv-ros2/install.log 2>&1 &
ros2_install=$!
# a run that ends first (a few tests) stops the install too: no process outlives this script (the
# next run starts it again)
trap 'kill -- "-$ros2_install" 2>/dev/null || true' EXIT
.venv/bin/ruff check .
# the tests that measure speed or wall-clock timing (marked serial) alone on the machine, then the rest
# two at a time (HILSIM_TEST_WORKERS): most of them wait on real processes, and the suite fits its
# budget only so. Exit code 5 (no test selected, e.g. a file of one kind) is not a failure.
rc=0
# (--durations: the slowest of each part in the output, so a run over its budget says where the time went)
.venv/bin/python -m pytest -q -m serial --durations=15 "$@" || { r=$?; [ "$r" -eq 5 ] || rc=$r; }
.venv/bin/python -m pytest -q -m "not serial" -n "${HILSIM_TEST_WORKERS:-2}" --durations=40 "$@" || { r=$?; [ "$r" -eq 5 ] || rc=$r; }
exit $rc
