"""hilsim: a distributed robot simulator over Zenoh with hardware in the loop."""

import os

# One worker thread per Zenoh runtime pool instead of one per core and pool: every hilsim
# process is small, and on a 2-core machine six processes' idle pools cost context switches
# (the lockstep loop ran ~15 % faster; docs/performance.md). Read when the first session opens;
# a user's own ZENOH_RUNTIME wins.
os.environ.setdefault(
    "ZENOH_RUNTIME",
    "(app: (worker_threads: 1), acc: (worker_threads: 1), tx: (worker_threads: 1), "
    "rx: (worker_threads: 1), net: (worker_threads: 1))",
)

__version__ = "0.1.0"
