# Sourced by scripts/arm.sh and scripts/test.sh: `ensure_venv SPEC` makes .venv/ (if needed) and
# installs hilsim into it (editable, `pip install -e SPEC`: `.` or `.[test]`) once, and again only
# when pyproject.toml changes or SPEC asks for more: the hash of pyproject.toml and the SPEC installed
# are kept in .venv/.hilsim-installed. Every other call runs no pip at all (pip would reach for the
# package index each time: half a minute of retries offline).
#
# The install says how long it takes and shows its progress on stderr: a phase line with the
# estimate, then one line per package pip takes (its "Collecting" lines, counted, with the seconds
# so far), the long "Installing collected packages" step announced, and the total time. pip's whole
# output goes to .venv/pip-install.log; when pip fails, its last lines are shown.
# measured: .[test] into a fresh .venv, pip's cache warm, on a 2-core machine shared with other work: pip
# installed 82 packages ("Installing collected packages: …", dependencies included) in 265 s
VENV_ESTIMATE="about 4 minutes on a 2-core machine (265 s measured for .[test], 82 packages)"

_pip_progress() {
  local t0="$1" n=0 line
  while IFS= read -r line; do
    case "$line" in
      Collecting*|Obtaining*)
        n=$((n + 1))
        printf '  [%3d s] %3d: %s\n' "$((SECONDS - t0))" "$n" "$line" ;;
      "Installing collected packages"*)
        # what pip installs is this line's list (dependencies too), not the requirements it collected
        n="$(printf '%s\n' "${line#*: }" | tr ',' '\n' | grep -c .)"
        printf '  [%3d s] installing %d packages into .venv (a minute or two, no output meanwhile)\n' \
          "$((SECONDS - t0))" "$n" ;;
      "Successfully installed"*)
        printf '  [%3d s] done\n' "$((SECONDS - t0))" ;;
    esac
  done
}

ensure_venv() {
  local spec="$1" stamp=.venv/.hilsim-installed hash have t0 rc
  if [ ! -x .venv/bin/python ]; then
    echo "creating .venv (python3 -m venv)" >&2
    python3 -m venv .venv
  fi
  hash="$(python3 -c 'import hashlib,sys; print(hashlib.sha256(open(sys.argv[1],"rb").read()).hexdigest())' \
    pyproject.toml)"
  have="$(cat "$stamp" 2>/dev/null || true)"
  # up to date: the same pyproject.toml, installed with this SPEC (or with the test extras, a superset)
  if [ "$have" = "$hash $spec" ] || { [ "$spec" = "." ] && [ "$have" = "$hash .[test]" ]; }; then
    return 0
  fi
  echo "installing hilsim into .venv (pip install -e '$spec'; once, and again when pyproject.toml changes):" \
    "the first time $VENV_ESTIMATE; pip's log: .venv/pip-install.log" >&2
  t0=$SECONDS
  # pip's exit code through a file: the pipeline's own is the filter's, and errexit must not cut it short
  { .venv/bin/python -m pip install -e "$spec" 2>&1 && echo 0 > .venv/.pip-rc || echo $? > .venv/.pip-rc; } \
    | tee .venv/pip-install.log | _pip_progress "$t0" >&2
  rc="$(cat .venv/.pip-rc)"
  rm -f .venv/.pip-rc
  if [ "$rc" -ne 0 ]; then
    echo "pip install -e '$spec' failed (exit code $rc) after $((SECONDS - t0)) s; its last lines" \
      "(all of it in .venv/pip-install.log):" >&2
    grep -v "is ignored: it is neither a file nor a directory" .venv/pip-install.log | tail -n 15 >&2
    return "$rc"
  fi
  echo "hilsim installed into .venv in $((SECONDS - t0)) s" >&2
  echo "$hash $spec" > "$stamp"
}
