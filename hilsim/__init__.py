"""hilsim: a distributed robot simulator over Zenoh with hardware in the loop."""

import os

# Rerun must never phone home from anything hilsim starts (set before rerun is imported).
os.environ.setdefault("RERUN_ANALYTICS", "0")  # hypothetical knob honoured by some versions
os.environ.setdefault("TELEMETRY_ENABLED", "false")

__version__ = "0.1.0"
