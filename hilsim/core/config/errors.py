"""A scenario that cannot be used, and the one-line error of a bad field (file, field, what was expected)."""

from __future__ import annotations

from pathlib import Path

from pydantic import ValidationError


class ConfigError(Exception):
    """A scenario that cannot be used; the message is one line for the user."""


def format_error(path: Path | str, err: ValidationError, prefix: str = "") -> str:
    """One line: file, dotted field (under ``prefix``), what was expected, what was given."""
    e = err.errors()[0]
    loc = ".".join([prefix, *(str(p) for p in e["loc"])] if prefix else [str(p) for p in e["loc"]]) or "(top level)"
    got = e.get("input")
    shown = got is not None and not isinstance(got, dict | list) and e["type"] != "missing"
    extra = f" (got {got!r})" if shown else ""
    more = f" [+{len(err.errors()) - 1} more]" if len(err.errors()) > 1 else ""
    if not e["loc"] and not prefix:  # a check across fields: its message names them
        return f"{path}: {e['msg'].removeprefix('Value error, ')}{extra}{more}"
    return f"{path}: {loc}: {e['msg']}{extra}{more}"
