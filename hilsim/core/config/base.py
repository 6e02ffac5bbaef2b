"""What every scenario schema shares: the repository's folders, the default services, the name of a joint
simulated by physics, sizes in bytes, the registry's service names in pydantic's validation context, and the
base model (unknown fields refused, assignments validated)."""

from __future__ import annotations

import math
from pathlib import Path

from pydantic import BaseModel, ConfigDict, ValidationInfo

REPO_ROOT = Path(__file__).resolve().parents[3]
CONFIG_DIR = REPO_ROOT / "config"
MODELS_DIR = REPO_ROOT / "models"

DEFAULT_SERVICES = ("physics", "sensors", "controller", "planner", "logger")
SIM = "sim"  # the server of a joint simulated by physics


def known_services(info: ValidationInfo) -> list[str] | None:
    """The service names the registry knows, as the loader (:mod:`hilsim.core.scenario`) passes them in the
    validation context (the schema does not import the registry, which sits above it); None: not checked."""
    ctx = info.context
    return ctx.get("services") if isinstance(ctx, dict) else None


_UNITS = {"": 1, "b": 1, "kb": 1000, "mb": 1000**2, "gb": 1000**3, "tb": 1000**4,
          "kib": 1024, "mib": 1024**2, "gib": 1024**3, "tib": 1024**4}


def parse_bytes(text: str) -> int:
    """``'500MB'`` -> 500000000, ``'2 GiB'`` -> 2147483648, ``'1024'`` -> 1024 (a size in a scenario)."""
    t = text.strip().lower().replace(" ", "")
    num = t.rstrip("abcdefghijklmnopqrstuvwxyz")
    unit = t[len(num):]
    try:
        value = float(num)
    except ValueError:
        value = -1.0
    if unit not in _UNITS or value < 0 or not math.isfinite(value):
        raise ValueError(f"expected a size in bytes, e.g. 500000000, '500MB' or '2GiB', got {text!r}")
    return int(value * _UNITS[unit])


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)
