#!/usr/bin/env bash
# The README's HIL demos, N runs each, beside a load of L busy processes (docs/hil.md, "On a busy
# machine"): `bash scripts/demo-under-load.sh [can|mavlink|both] [N=10] [L=4] [OUT=/tmp/hilsim-under-load]`.
# Prints one line per run (exit code, seconds, targets, result) and the count of OK runs; exits 1 if
# any run did not end `result: OK`. Each run keeps its directory (OUT/<demo><i>) and output (.log).
set -uo pipefail
cd "$(dirname "$0")/.."
which=${1:-both}; n=${2:-10}; load=${3:-4}; out=${4:-/tmp/hilsim-under-load}
case $which in can|mavlink|both) ;; *) echo "usage: $0 [can|mavlink|both] [N] [LOAD] [OUT]" >&2; exit 2 ;; esac
source scripts/venv.sh
ensure_venv .
mkdir -p "$out"
busy=()
stop() { kill "${busy[@]}" 2>/dev/null; }
trap stop EXIT
for _ in $(seq 1 "$load"); do python3 -c 'while True: pass' & busy+=($!); done
ok=0; runs=0
run() {  # run NAME I COMMAND...
  local name=$1 i=$2; shift 2
  local dir="$out/$name$i" s rc
  rm -rf "$dir" "$dir.log"
  s=$(date +%s)
  "$@" --out "$dir" > "$dir.log" 2>&1
  rc=$?
  runs=$((runs + 1))
  grep -q '^result: OK' "$dir.log" && ok=$((ok + 1))
  echo "$name $i: exit $rc, $(( $(date +%s) - s )) s, $(grep -E 'targets reached|^result:' "$dir.log" | tr -s ' \n' ' ')"
}
if [[ $which != mavlink ]]; then
  for i in $(seq 1 "$n"); do run can "$i" .venv/bin/hilsim up arm --hil config/hil/can-emulated.yaml; done
fi
if [[ $which != can ]]; then
  for i in $(seq 1 "$n"); do
    run mavlink "$i" .venv/bin/hilsim up rover --world outdoor --hil config/hil/mavlink-emulated.yaml
  done
fi
echo "$ok of $runs runs: result OK (beside $load busy processes; logs in $out)"
[[ $ok == "$runs" ]]
