"""``hilsim plan evaluate``: plan several targets of a scenario and compare them.

An arm scenario (joint targets, the paper's Table III): :mod:`hilsim.tools.planning_eval.arm`; a mobile
robot (a scenario with a navigator; the rover's goals): :mod:`hilsim.tools.planning_eval.rover`. What both
share (the criteria and the choice of the best, where the CSV goes): :mod:`hilsim.tools.planning_eval.common`.
Planners compared on the queries of a scenes file (``--scenes``, the learned choice ``auto`` among
them): :mod:`hilsim.tools.planning_eval.scenes`.
"""

from __future__ import annotations

import argparse


def cmd_evaluate(args: argparse.Namespace) -> int:
    from hilsim.core.scenario import load_scenario
    from hilsim.planning import quiet_ompl_at_exit

    quiet_ompl_at_exit()
    sc = load_scenario(args.scenario)
    if getattr(args, "scenes", None):  # planners compared on a scenes file's queries
        from hilsim.tools.planning_eval.scenes import cmd_evaluate_scenes

        return cmd_evaluate_scenes(sc, args)
    if "navigator" in sc.services:  # a mobile robot: rover goals
        from hilsim.tools.planning_eval.rover import cmd_evaluate_goals

        return cmd_evaluate_goals(sc, args)
    from hilsim.tools.planning_eval.arm import cmd_evaluate_targets

    return cmd_evaluate_targets(sc, args)
