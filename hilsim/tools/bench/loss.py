"""``hilsim bench loss``: what a realtime run's recording misses when other runs share the machine,
against the same run alone, measured in the same invocation.

Each round starts ``hilsim up SCENARIO --clock realtime --duration S --allow-loss`` once alone (the
baseline), then ``--runs N`` of them at once (each its own run directory and router: ``hilsim up``
takes a free port when 7447 is taken), and reads for every run what its summary judges
(:mod:`hilsim.launch.summary`): the samples the recorder received (``record_summary.json``), those it
lost (dropped at its full queue, and gaps in the writers' sequence numbers) and the published samples
that never reached it (the ``N published samples never reached the recorder`` line). The figure is the
summary's: ``missed / (received + missed)``, the share checked against ``logger.max_loss``
(``--allow-loss`` so that a lossy run still ends normally and is measured). ``--repeat K`` rounds.

Reads and writes no key itself: the runs are ordinary ``hilsim up`` processes.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

from hilsim.core.recording import read_counts

UNSEEN = re.compile(r"^\s+(\d+) published samples never reached the recorder", re.M)
RESULT = re.compile(r"^result: (.*)$", re.M)
RTF = re.compile(r"real-time factor ([0-9.]+)")


def _start(scenario: str, seconds: float, run_dir: Path) -> subprocess.Popen[str]:
    argv = [sys.executable, "-m", "hilsim.cli", "up", scenario, "--clock", "realtime", "--duration", f"{seconds:g}",
            "--allow-loss", "--out", str(run_dir)]
    return subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)


def _figures(run_dir: Path, out: str, rc: int) -> dict[str, Any]:
    """One run's recording: received, lost, never reached, the share missed (as its summary judges it)."""
    fig: dict[str, Any] = {"run_dir": str(run_dir), "exit": rc}
    m = RESULT.search(out)
    fig["result"] = m[1] if m else "?"
    r = RTF.search(out)
    fig["real_time_factor"] = float(r[1]) if r else None
    try:
        counts, _ = read_counts(run_dir)
    except (OSError, ValueError):
        fig["error"] = "no record_summary.json"
        return fig
    received = sum(v.get("received", 0) for v in counts.values())
    recorded = sum(v.get("recorded", 0) for v in counts.values())
    lost = sum(v.get("lost", 0) for v in counts.values())
    dropped = sum(min(v.get("dropped", 0), v.get("lost", 0)) for v in counts.values())
    unseen = sum(int(n) for n in UNSEEN.findall(out))
    missed = lost + unseen
    fig.update(received=received, recorded=recorded, lost=lost, dropped_by_recorder=dropped,
               lost_in_transport=lost - dropped, never_reached=unseen, missed=missed,
               missed_share=missed / max(1, received + missed))
    return fig


def _round(scenario: str, seconds: float, n: int, base: Path, tag: str, timeout: float) -> list[dict[str, Any]]:
    """``n`` runs started together; their figures once all ended."""
    dirs = [base / f"{tag}-{i}" for i in range(n)]
    procs = [_start(scenario, seconds, d) for d in dirs]
    figs = []
    for d, p in zip(dirs, procs, strict=True):
        try:
            out, _ = p.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, 9)
            out, _ = p.communicate()
            out += "\nresult: KILLED (bench timeout)"
        figs.append(_figures(d, out, p.returncode))
    return figs


def _line(label: str, f: dict[str, Any]) -> str:
    if "missed_share" not in f:
        return f"  {label}: {f.get('error', '?')} ({f['result']})"
    return (f"  {label}: missed {f['missed_share']:.2%} ({f['missed']} of {f['received'] + f['missed']}: "
            f"{f['dropped_by_recorder']} dropped by the recorder, {f['lost_in_transport']} lost in transport, "
            f"{f['never_reached']} never reached it); recorded {f['recorded']} of {f['received']} received; "
            f"real-time factor {f['real_time_factor']}; {f['result']}")


def cmd_loss(args: argparse.Namespace) -> int:
    """``hilsim bench loss``: see the module docstring."""
    if args.runs < 2 or args.repeat < 1 or args.seconds <= 0:
        print("hilsim bench loss: --runs must be >= 2, --repeat >= 1, --seconds > 0", file=sys.stderr)
        return 2
    rounds: list[dict[str, Any]] = []
    timeout = args.seconds * 10 + 180
    with TemporaryDirectory(prefix="hilsim-bench-loss-") as tmp:
        base = Path(args.keep) if args.keep else Path(tmp)
        base.mkdir(parents=True, exist_ok=True)
        for k in range(args.repeat):
            load = os.getloadavg()[0]
            t0 = time.monotonic()
            alone = _round(args.scenario, args.seconds, 1, base, f"r{k}-alone", timeout)[0]
            together = _round(args.scenario, args.seconds, args.runs, base, f"r{k}-together", timeout)
            rounds.append({"round": k + 1, "load_before": round(load, 2), "alone": alone, "together": together,
                           "wall_s": round(time.monotonic() - t0, 1)})
            if not args.json:
                print(f"round {k + 1} (load average before: {load:.2f}):", flush=True)
                print(_line("alone", alone), flush=True)
                for i, f in enumerate(together):
                    print(_line(f"{args.runs} at once, run {i + 1}", f), flush=True)
    shares = [f["missed_share"] for r in rounds for f in r["together"] if "missed_share" in f]
    alone_shares = [r["alone"]["missed_share"] for r in rounds if "missed_share" in r["alone"]]
    result = {"scenario": args.scenario, "seconds": args.seconds, "runs": args.runs, "rounds": rounds,
              "alone_max_share": max(alone_shares, default=None), "together_max_share": max(shares, default=None)}
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        print(f"missed, worst: alone {_pct(result['alone_max_share'])}, {args.runs} at once "
              f"{_pct(result['together_max_share'])} (logger.max_loss as shipped: 5 %)")
    return 0


def _pct(x: float | None) -> str:
    return "?" if x is None else f"{x:.2%}"
