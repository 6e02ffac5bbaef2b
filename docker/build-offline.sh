#!/usr/bin/env bash
# Build the hilsim image without a registry or a package index reachable from inside the build:
#   bash docker/build-offline.sh [--base-only]
# 1. the base image (BASE, default localhost/hilsim-base:bookworm), only when missing: a minimal
#    Debian 12 with python3 made by mmdebstrap from the host's apt mirror (~20 s) and imported;
# 2. wheels of every dependency, built on the host with its own pip configuration (indexes, proxy,
#    certificates) into WHEELS (default ~/.cache/hilsim-wheels, outside the repository, kept
#    between builds; with everything already there pip needs no network at all);
# 3. the image (IMAGE, default hilsim:latest) from docker/Dockerfile with those two, built with no
#    network. Layers are cached: after a code change only the last steps run again.
# The engine is podman (ENGINE=docker for Docker with buildx). `docker compose … up` / podman-compose
# then use the image as it is (they build only when it is missing).
set -euo pipefail
cd "$(dirname "$0")/.."
ENGINE="${ENGINE:-podman}"
BASE="${BASE:-localhost/hilsim-base:bookworm}"
IMAGE="${IMAGE:-hilsim:latest}"
WHEELS="${WHEELS:-$HOME/.cache/hilsim-wheels}"
PYTHON="${PYTHON:-$( [ -x .venv/bin/python ] && echo .venv/bin/python || echo python3 )}"
say() { echo "docker/build-offline.sh: $*" >&2; }

if ! "$ENGINE" image exists "$BASE" 2>/dev/null && ! "$ENGINE" image inspect "$BASE" >/dev/null 2>&1; then
  command -v mmdebstrap >/dev/null || { say "mmdebstrap is missing (apt-get install mmdebstrap)"; exit 1; }
  # the mirror apt already uses (deb822 sources or a sources.list line), so no other network is needed
  mirror="$(sed -n 's/^URIs: *\([^ ]*\).*/\1/p' /etc/apt/sources.list.d/*.sources 2>/dev/null | grep -v security | head -1)"
  [ -n "$mirror" ] || mirror="$(awk '$1 == "deb" && $3 == "bookworm" {print $2; exit}' /etc/apt/sources.list 2>/dev/null)"
  mirror="${mirror:-http://deb.debian.org/debian}"
  tmp="$(mktemp -d)"
  trap 'rm -rf "$tmp"' EXIT
  say "building the base image $BASE from $mirror (mmdebstrap, ~20 s)"
  mmdebstrap --quiet --variant=minbase --include=python3,python3-venv,python3-pip,ca-certificates \
    bookworm "$tmp/base.tar" "$mirror"
  "$ENGINE" import --quiet "$tmp/base.tar" "$BASE" >/dev/null
  rm -rf "$tmp"
  trap - EXIT
fi
[ "${1:-}" = "--base-only" ] && exit 0

# the dependencies, as pyproject.toml lists them, at the versions the host's .venv runs (if any)
mkdir -p "$WHEELS"
req="$(mktemp)"
cons="$(mktemp)"
trap 'rm -f "$req" "$cons"' EXIT
"$PYTHON" -c "import tomllib; print(*tomllib.load(open('pyproject.toml', 'rb'))['project']['dependencies'], sep='\n')" > "$req"
echo 'setuptools>=69' >> "$req"
echo wheel >> "$req"
"$PYTHON" -m pip freeze --exclude-editable 2>/dev/null | grep -v '^-e ' > "$cons" || true
if ! "$PYTHON" -m pip wheel -q --no-index --find-links "$WHEELS" -w "$WHEELS" -r "$req" -c "$cons" >/dev/null 2>&1; then
  say "building wheels into $WHEELS (pip wheel, with this host's pip configuration)"
  # (without the host's notes on its file:// indexes that lack a package: one line per package)
  "$PYTHON" -m pip wheel -q --find-links "$WHEELS" -w "$WHEELS" -r "$req" -c "$cons" 2>&1 \
    | { grep -v "^WARNING: Location 'file:" || true; } >&2
fi

say "building $IMAGE (FROM $BASE, wheels from $WHEELS, no network)"
old="$("$ENGINE" image inspect --format '{{.Id}}' "$IMAGE" 2>/dev/null || true)"
"$ENGINE" build --quiet -f docker/Dockerfile --network none \
  --build-arg BASE_IMAGE="$BASE" --build-context wheels="$WHEELS" -t "$IMAGE" . >/dev/null
new="$("$ENGINE" image inspect --format '{{.Id}}' "$IMAGE")"
# the image it replaced, untagged now: removed, so that builds after each change do not pile up
if [ -n "$old" ] && [ "$old" != "$new" ]; then
  "$ENGINE" rmi "$old" >/dev/null 2>&1 || true
fi
say "built $IMAGE"
