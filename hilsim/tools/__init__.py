"""The ``hilsim`` commands a user runs beside a simulation, grouped by what the user does (each group a
folder; ``hilsim --help`` lists the commands under the same words):

- :mod:`.recording`: what to do with a recording: play a bag again, export a run, a bag's info, recovery
  and differences (``hilsim play``, ``export``, ``bag``);
- :mod:`.inspection`: looking at and poking a running simulation: its topics and the controller's
  gains (``hilsim topic``, ``gains``);
- :mod:`.tuning`: tuning and identification: step experiments on the real services, the step-response
  report, PID auto-tuning, inertia from primitives, and a real drive identified into a twin (``hilsim
  report step``, ``tune``, ``inertia``, ``identify``);
- :mod:`.planning_eval`: planning evaluation and the learned planner choice (``hilsim plan evaluate``,
  ``plan learn``, ``plan scenes``);
- :mod:`.bench`: the benchmarks (``hilsim bench loop|rover|scale|loss|ros2``), each a ratio against a
  baseline measured in the same run;
- :mod:`.robot`: a robot imported from its URDF (``hilsim robot import``), with :mod:`.examples`, its
  example files.

What every command shares: :func:`progress`, its progress lines."""

from __future__ import annotations

from collections.abc import Callable


def progress(quiet: bool) -> Callable[[str], None]:
    """A command's progress lines: each printed (and flushed) as it comes, none when ``quiet``
    (``--json``: stdout is the JSON then)."""

    def say(text: str) -> None:
        if not quiet:
            print(text, flush=True)

    return say
