"""``hilsim bag info BAG`` and ``hilsim bag recover BAG``: a recorded bag's contents, and making the bag
of a killed recorder whole (:mod:`hilsim.record.bag_read`).

``BAG`` is a run directory, its ``bag/`` directory or one ``.mcap`` file. A missing or unreadable bag
is one line on standard error and exit code 1.
"""

from __future__ import annotations

import argparse
import sys

from hilsim.record.bag import BagError
from hilsim.record.bag_read import info, recover_bag


def cmd_info(args: argparse.Namespace) -> int:
    try:
        print(info(args.bag))
    except BagError as e:
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
