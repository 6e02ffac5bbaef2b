# Sourced by scripts/arm.sh and scripts/test.sh: `ensure_venv SPEC` makes .venv/ (if needed) and
# installs hilsim into it (editable, `pip install -q -e SPEC`: `.` or `.[test]`) once, and again only
# when pyproject.toml changes or SPEC asks for more: the hash of pyproject.toml and the SPEC installed
# are kept in .venv/.hilsim-installed. Every other call runs no pip at all (pip would reach for the
# package index each time: half a minute of retries offline).
ensure_venv() {
  local spec="$1" stamp=.venv/.hilsim-installed hash have
  if [ ! -x .venv/bin/python ]; then
    python3 -m venv .venv
  fi
  hash="$(python3 -c 'import hashlib,sys; print(hashlib.sha256(open(sys.argv[1],"rb").read()).hexdigest())' \
    pyproject.toml)"
  have="$(cat "$stamp" 2>/dev/null || true)"
  # up to date: the same pyproject.toml, installed with this SPEC (or with the test extras, a superset)
  if [ "$have" = "$hash $spec" ] || { [ "$spec" = "." ] && [ "$have" = "$hash .[test]" ]; }; then
    return 0
  fi
  echo "installing hilsim into .venv (pip install -e '$spec'; once, and again when pyproject.toml changes)" >&2
  .venv/bin/python -m pip install -q -e "$spec"
  echo "$hash $spec" > "$stamp"
}
