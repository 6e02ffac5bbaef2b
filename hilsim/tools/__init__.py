"""The arm paper's engineering tools: inertia from primitives (:mod:`.inertia`), step-response
figures (:mod:`.metrics`), step experiments on the real services in lockstep (:mod:`.rig`), the
Table II report (:mod:`.step_report`) and PID auto-tuning (:mod:`.tuning`); and the benchmarks,
introspection and evaluation commands of ``hilsim``."""

from __future__ import annotations

from collections.abc import Callable


def progress(quiet: bool) -> Callable[[str], None]:
    """A command's progress lines: each printed (and flushed) as it comes, none when ``quiet``
    (``--json``: stdout is the JSON then)."""

    def say(text: str) -> None:
        if not quiet:
            print(text, flush=True)

    return say
