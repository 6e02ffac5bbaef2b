"""``hilsim bag info [BAG]``, ``hilsim bag recover BAG`` and ``hilsim bag diff A B``: a recorded bag's
contents, making the bag of a killed recorder whole (:mod:`hilsim.record.bag_read`), and where two bags
first differ (:mod:`hilsim.record.bag_diff`).

``BAG`` is a run directory, its ``bag/`` directory or one ``.mcap`` file; ``bag info`` without one takes
the latest run under ``runs/``. A missing or unreadable bag is one line on standard error and exit code 1
(``diff``: 2, as diff(1) does; 1 there means the bags differ).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hilsim.record.bag import BagError
from hilsim.record.bag_read import info, recover_bag

DIFF_SHOWN = 20  # topics listed by bag diff at most


def latest_run(runs: str) -> Path:
    """The newest run directory under ``runs`` (by its recording's time, as ``hilsim view`` takes it); raises
    :class:`hilsim.core.recording.RecordingError` if there is none."""
    from hilsim.core.recording import latest_recording

    return latest_recording(runs).parent


def cmd_info(args: argparse.Namespace) -> int:
    from hilsim.core.recording import RecordingError

    try:
        bag = args.bag
        if bag is None:
            bag = latest_run(args.runs)
            print(f"hilsim bag info: the latest run, {bag}", file=sys.stderr)
        print(info(bag))
    except (BagError, RecordingError) as e:
        print(f"hilsim bag info: {str(e).splitlines()[0]}", file=sys.stderr)
        return 1
    return 0


def cmd_recover(args: argparse.Namespace) -> int:
    try:
        done = recover_bag(args.bag)
    except BagError as e:
        print(f"hilsim bag recover: {str(e).splitlines()[0]}", file=sys.stderr)
        return 1
    for r in done:
        if r.rewritten:
            cut = f"; {r.dropped_bytes} bytes of a record cut by the kill left out" if r.dropped_bytes else ""
            print(f"{r.path}: recovered, {r.messages} messages{cut}")
        else:
            print(f"{r.path}: complete, {r.messages} messages (left as it was)")
    print(f"{done[0].path.parent / 'metadata.yaml'}: written")
    return 0


def cmd_diff(args: argparse.Namespace) -> int:
    """0: the bags hold the same messages (wall-clock topics and fields aside); 1: they differ (the first
    difference first, then each topic's first); 2: a bag cannot be read."""
    from hilsim.record.bag_diff import diff

    try:
        found = diff(args.a, args.b, everything=args.all, ignore=args.ignore or ())
    except BagError as e:
        print(f"hilsim bag diff: {str(e).splitlines()[0]}", file=sys.stderr)
        return 2
    if not found:
        left = "" if args.all else " (health and logs, wall-clock by nature, left out: --all compares them)"
        print(f"the bags hold the same messages{left}")
        return 0
    print(f"the bags differ on {len(found)} topics; first at t={found[0].sim_ns / 1e9:.3f} s sim:")
    for d in found[:DIFF_SHOWN]:
        print(f"  {d.line()}")
    if len(found) > DIFF_SHOWN:
        print(f"  … and {len(found) - DIFF_SHOWN} more topics")
    return 1
