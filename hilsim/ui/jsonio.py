"""The panel's JSON in and out: a refused request (:class:`BadInput`, answered as a 4xx with
``{"error", "field"}``), numbers read from a request body, and states made valid JSON for the browser.

No Zenoh keys: pure checks and conversions, used by every other module of :mod:`hilsim.ui`.
"""

from __future__ import annotations

import math
from typing import Any


class BadInput(ValueError):
    """A request the panel refuses: the message is shown beside ``field`` in the page."""

    def __init__(self, fld: str, message: str, status: int = 400) -> None:
        super().__init__(message)
        self.field = fld
        self.status = status


def number(body: dict[str, Any], name: str, fld: str | None = None, *, required: bool = True) -> float | None:
    """A finite number from a JSON body (a number or a numeric string), else BadInput on ``fld``."""
    v = body.get(name)
    if v is None or (isinstance(v, str) and not v.strip()):
        if required:
            raise BadInput(fld or name, f"{name}: a number is required")
        return None
    if isinstance(v, bool):
        raise BadInput(fld or name, f"{name}: expected a number, got {v!r}")
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise BadInput(fld or name, f"{name}: expected a number, got {str(v)[:40]!r}") from None
    if not math.isfinite(x):
        raise BadInput(fld or name, f"{name}: expected a finite number, got {v!r}")
    return x


def finite(x: Any) -> Any:
    """JSON without NaN/inf (the browser's JSON.parse refuses them): null instead."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: finite(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [finite(v) for v in x]
    return x
