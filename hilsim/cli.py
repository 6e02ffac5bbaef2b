"""The ``hilsim`` command: one entry for running, inspecting and measuring simulations.

    hilsim up SCENARIO [--clock lockstep|realtime] [--duration S | --interactive] [--seed N] [--only A,B --router EP]
    hilsim run SERVICE --config FILE
    hilsim topic list | echo KEY [--count N] [--json] | hz KEY
    hilsim view [RRD] | --live [--run DIR]
    hilsim play BAG [--rate R] [--keys PATTERN] [--loop] [--clock]
    hilsim bag info|recover BAG
    hilsim export RUN --to mcap|csv [--out DIR]
    hilsim goal ROBOT --joints J1 … | --pose X Y Z [R P Y] | --xy X Y [--yaw THETA]
    hilsim gains ROBOT JOINT.GAIN=VALUE …
    hilsim plan evaluate --targets FILE [--criterion length|smoothness|weighted]
    hilsim plan evaluate --scenes FILE [--planners NAMES] [--criterion C] [--json]
    hilsim plan learn [--out DIR] [--seed N] [--scenes N] [--queries K] [--seeds S] [--train-only]
    hilsim plan scenes --out DIR [--count N] [--seed S] [--queries K]
    hilsim bench loop|plan|can|mavlink|rover|ros2 [--json]
    hilsim bench loss [--runs 2] [--repeat 3] [--seconds S] [--json]
    hilsim bench scale [--robots 1,2,4,8] [--subscribers 0,4] [--sim-seconds S] [--repeat K] [--compose] [--json]
    hilsim report step ROBOT [--joints J,…] [--step RAD] [--speed RAD/S] [--hil FILE] [--json]
    hilsim identify SCENARIO|RUN_DIR --joints J[,…] [--write FILE] [--json]
    hilsim inertia FILE [--link NAME] [--urdf FILE] [--json]
    hilsim robot import URDF [--package-path DIR]… [--name NAME] [--out DIR] [--tool LINK] [--srdf FILE]
    hilsim tune ROBOT JOINT|--all [--method ziegler-nichols|relay] [--write] [--json]
    hilsim router [--listen ENDPOINT] [--config FILE]
    hilsim compose SCENARIO [--hil FILE]… [--out docker/compose.yaml]
    hilsim ui [--host H] [--port P] [--connect EP]
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence
from typing import get_args

from hilsim import __version__
from hilsim.core.config import DEFAULT_CRITERION, ConfigError, Criterion
from hilsim.core.scenario import load_scenario, parse_overrides


def cmd_run(args: argparse.Namespace) -> int:
    from hilsim.core.registry import UnknownService, service_class
    from hilsim.core.service import setup_logging

    setup_logging(args.service, logging.DEBUG if args.verbose else logging.INFO)
    names = args.service.split("+")  # a+b+c: composed in one process (hilsim.launch.compose)
    try:
        for n in names:
            service_class(n.split("@")[0])  # an unknown name is said before the scenario is read
    except UnknownService as e:
        print(f"hilsim run: {e}", file=sys.stderr)
        return 2
    sc = load_scenario(args.config, parse_overrides(args.set))
    from hilsim.core import fleet
    from hilsim.core.service import instantiate

    # robots > 1: controller@arm3 is one robot's controller, controller@* every robot's (hilsim.core.fleet)
    names = fleet.members(sc, args.service)
    if len(names) > 1:
        from hilsim.launch import compose

        return compose.run(names, sc)
    return int(instantiate(names[0], sc).run())


def _lazy(module: str, func: str) -> Callable[[argparse.Namespace], int]:
    def call(args: argparse.Namespace) -> int:
        import importlib

        return int(getattr(importlib.import_module(module), func)(args))

    return call


def _lazy_ints(text: str) -> list[int]:
    from hilsim.tools.bench.scale import _ints

    return _ints(text)


def _endpoint_args(p: argparse.ArgumentParser) -> None:
    """--connect / --prefix of the tools that join a running simulation (hilsim.core.transport.tool_*)."""
    p.add_argument("--connect", help="Zenoh endpoint(s), comma-separated "
                   "(default: HILSIM_ZENOH_CONNECT, else the one run of yours that is up, else tcp/127.0.0.1:7447)")
    p.add_argument("--prefix", default=None, help="key prefix (default: HILSIM_PREFIX, else hilsim)")
    p.add_argument("--run", metavar="DIR", help="join the run of yours that is up in DIR (its router and "
                   "credentials; default: the one run of yours that is up, asked if there are several)")


def _view(args: argparse.Namespace) -> int:
    """``hilsim view``: a recording, or ``--live`` a run that is up (hilsim.record.live_viewer)."""
    if args.live:
        return _lazy("hilsim.record.live_viewer", "cmd_view_live")(args)
    return _lazy("hilsim.core.recording", "cmd_view")(args)


def _up(args: argparse.Namespace) -> int:
    """``hilsim up``; with ``--ui`` the panel starts the run and stays (hilsim.ui.server)."""
    return _lazy("hilsim.ui.server", "cmd_up_ui")(args) if args.ui else _lazy("hilsim.launch.up", "cmd_up")(args)


# the commands by what the user does; the tools' folders (hilsim/tools/) use the same words
_GROUPS = """commands by what you do:
  running             up, run, view, goal, compose, router, creds, ui
  recording           play, export, bag                       (hilsim/tools/recording/)
  inspection          topic, gains                            (hilsim/tools/inspection/)
  tuning              report step, tune, inertia, identify    (hilsim/tools/tuning/)
  planning evaluation plan evaluate, plan learn, plan scenes  (hilsim/tools/planning_eval/)
  benchmarks          bench loop|rover|scale|loss|ros2        (hilsim/tools/bench/)
                      bench plan|choice, bench can|mavlink    (beside what they measure: planning/, bridges/)
  robots              robot import                            (hilsim/tools/robot/)"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="hilsim", description="Distributed robot simulator over Zenoh.",
                                epilog=_GROUPS, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.add_argument("--version", action="version", version=f"hilsim {__version__}", help="print the version and exit")
    sub = p.add_subparsers(dest="cmd", required=True)

    up = sub.add_parser("up", help="start all services of a scenario, run its task, stop, summarise")
    up.add_argument("scenario", help="scenario name in config/ (arm, arm-lean: the arm at half its rates, rover, "
                    "rover-outdoor) or a YAML path")
    up.add_argument("--clock", choices=["lockstep", "realtime"], help="override clock.mode (lockstep: as fast as "
                    "every service allows, deterministic; realtime: paced by the wall clock; default the scenario's, "
                    "the arm's lockstep)")
    up.add_argument("--duration", type=float, help="stop after this many sim seconds (before the task ends: "
                    "result STOPPED, exit code 3)")
    up.add_argument("--interactive", action="store_true",
                    help="do not run the task: stay up until Ctrl-C, for hilsim goal, gains, topic and ROS 2 tools")
    up.add_argument("--seed", type=int, help="override the scenario seed")
    up.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="override any scenario field")
    up.add_argument("--out", help="run directory (default runs/<timestamp>)")
    up.add_argument("--no-logger", action="store_true", help="do not record (benchmarks)")
    up.add_argument("--allow-loss", action="store_true", help="realtime: a recording that missed more than "
                    "logger.max_loss (default 5 %%) of the samples is said, not a failure (sets logger.max_loss=1)")
    up.add_argument("--router", help="connect to this Zenoh router instead of starting one")
    up.add_argument("--world", help="the scenario's world, e.g. rover --world outdoor (config/rover-outdoor.yaml)")
    up.add_argument("--hil", "--overlay", dest="hil", action="append", default=[], metavar="FILE",
                    help="merge a file over the scenario, in order (e.g. config/hil/motor-model.yaml, "
                         "config/hil/can-emulated.yaml)")
    up.add_argument("--compose", action="append", default=[], metavar="A,B,...",
                    help="run these services in one process (e.g. physics,sensors,controller); repeatable")
    up.add_argument("--only", metavar="A,B,...",
                    help="start only these services here and wait for the others from other hosts "
                         "(docs/deployment.md); use with --router")
    up.add_argument("--wait", type=float, metavar="S",
                    help="seconds to wait for every service to announce itself (default: clock.start_timeout, 120)")
    up.add_argument("--view", action="store_true", help="watch it live: stream the run to Rerun's web viewer "
                    "(prints `viewer: URL`; docs/recording.md, \"Watch it live\")")
    up.add_argument("--foxglove", nargs="?", type=int, const=8765, metavar="PORT",
                    help="serve the run's ROS 2 topics over Foxglove's WebSocket protocol on loopback (default port "
                    "8765; prints `foxglove: ws://…`; docs/recording.md, \"Foxglove, live\")")
    up.add_argument("--view-wait", type=float, metavar="S", help="with --view and a task: seconds the run waits "
                    "for a viewer to open the page before it starts (default 120; 0: at once)")
    up.add_argument("--view-host", metavar="HOST", help="with --view: the viewer's address (default loopback; "
                    "another one asks a token, given in the URL)")
    up.add_argument("--ui", action="store_true", help="start the browser control panel with this run (docs/panel.md)")
    up.add_argument("--ui-host", default="127.0.0.1", help="with --ui: the panel's address (default loopback)")
    up.add_argument("--ui-port", type=int, default=8080, help="with --ui: the panel's port (default 8080)")
    up.add_argument("--ui-no-token", action="store_true", help="with --ui: serve the panel without a token")
    up.set_defaults(func=_up)

    run = sub.add_parser("run", help="run one service alone (what docker compose uses)")
    run.add_argument("service", help="physics, sensors, controller, planner, logger, or a bridge name")
    run.add_argument("--config", required=True, help="scenario YAML")
    run.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="override a scenario field; "
                     "repeatable")
    run.set_defaults(func=cmd_run)

    topic = sub.add_parser("topic", help="inspect topics like `ros2 topic` (ROS 2 names, rmw_zenoh keys)")
    tsub = topic.add_subparsers(dest="topic_cmd", required=True)
    for name in ("list", "echo", "hz"):
        t = tsub.add_parser(name, help={"list": "the topics of the run's ROS 2 graph (like ros2 topic list)",
                                        "echo": "print a topic's messages as they come (like ros2 topic echo)",
                                        "hz": "a topic's rate (like ros2 topic hz)"}[name])
        if name != "list":
            t.add_argument("key", help="a ROS 2 topic name, e.g. /arm/joint_states, or a Zenoh key expression")
        else:
            t.add_argument("--all", action="store_true", help="also hilsim's internal topics (health, sync, log, hw)")
            t.add_argument("-t", "--show-types", action="store_true", help="print each topic's type")
        t.add_argument("--domain", type=int, default=None, help="ROS 2 domain (default: ROS_DOMAIN_ID, else 0)")
        _endpoint_args(t)
        t.add_argument("--duration", type=float, default=None, help="wall seconds to listen (default: list 1 s, "
                       "echo and hz until Ctrl-C or --count)")
        if name == "echo":
            t.add_argument("--count", type=int, default=None, help="stop after this many messages (default: none)")
            t.add_argument("--json", action="store_true", help="one JSON object per message (default: YAML)")
        if name == "hz":
            t.add_argument("--window", type=int, default=1000, help="samples the rate is averaged over "
                           "(default 1000)")
            t.add_argument("--any-writer", action="store_true",
                           help="count every sample, not only those of the key's announced writer")
        t.set_defaults(func=_lazy("hilsim.tools.inspection.topic", f"cmd_{name}"))

    view = sub.add_parser("view", help="open the Rerun viewer on a recording (latest by default), or --live on a run")
    view.add_argument("rrd", nargs="?", help="a recording.rrd or its run directory (default: the latest run "
                      "under --runs)")
    view.add_argument("--runs", default="runs", help="where runs are, for the latest (default: runs)")
    view.add_argument("--live", action="store_true", help="the live viewer of a run that is up with --view: prints "
                      "`viewer: URL` (and opens the native viewer on it where there is a display)")
    view.add_argument("--run", metavar="DIR", help="with --live: the run's directory (default: the one run of yours "
                      "that is up)")
    view.set_defaults(func=_view)

    play = sub.add_parser("play", help="publish a recorded bag again on its keys, in sim time (like ros2 bag play)")
    play.add_argument("bag", help="a run directory, its bag/ directory or an .mcap file")
    play.add_argument("--rate", type=float, default=1.0, help="sim seconds per wall second (0: as fast as possible)")
    play.add_argument("--keys", help="only these: ROS 2 topic globs (/arm/joint_states, /arm/*) or Zenoh key "
                      "expressions (0/arm/**), comma-separated")
    play.add_argument("--loop", action="store_true", help="play again from the start until interrupted")
    play.add_argument("--clock", action="store_true", help="publish /clock from the stamps (the recorded one is "
                      "not played)")
    play.add_argument("--delay", type=float, default=0.5, help="seconds between announcing the publishers and "
                      "the first sample (default 0.5)")
    play.add_argument("--domain", type=int, default=None, help="ROS 2 domain to play into (default: the recorded one)")
    play.add_argument("--connect", help="Zenoh endpoint(s), comma-separated (default: HILSIM_ZENOH_CONNECT, "
                      "else the one run of yours that is up, else tcp/127.0.0.1:7447)")
    play.add_argument("--run", metavar="DIR", help="play into the run of yours that is up in DIR")
    play.set_defaults(func=_lazy("hilsim.tools.recording.play", "cmd_play"))

    bag = sub.add_parser("bag", help="a recorded bag (rosbag2, MCAP): what it holds, or make it whole")
    bsub_ = bag.add_subparsers(dest="bag_cmd", required=True)
    for name, text in (("info", "topics, types, counts, duration, start and end (like ros2 bag info)"),
                       ("recover", "rewrite the bag of a killed recorder from what reached the disk whole, and "
                                   "its metadata.yaml")):
        b = bsub_.add_parser(name, help=text)
        if name == "info":
            b.add_argument("bag", nargs="?", help="a run directory, its bag/ directory or an .mcap file (default: "
                           "the latest run under --runs)")
            b.add_argument("--runs", default="runs", help="where runs are, for the latest (default: runs)")
        else:
            b.add_argument("bag", help="a run directory, its bag/ directory or an .mcap file")
        b.set_defaults(func=_lazy("hilsim.tools.recording.bagtool", f"cmd_{name}"))
    d = bsub_.add_parser("diff", help="where two bags first differ (topic, sim time, field): exit 0 the same, "
                         "1 different, 2 unreadable")
    d.add_argument("a", help="a run directory, its bag/ directory or an .mcap file")
    d.add_argument("b", help="the other one")
    d.add_argument("--all", action="store_true", help="compare health, logs and wall-clock fields too (left out "
                   "by default: they differ between any two runs)")
    d.add_argument("--ignore", action="append", metavar="GLOB", help="leave out the topics matching this glob "
                   "(e.g. '/arm/planner/*'); repeatable")
    d.set_defaults(func=_lazy("hilsim.tools.recording.bagtool", "cmd_diff"))

    export = sub.add_parser("export", help="a run's Rerun recording as an MCAP bag or CSV files (runs recorded "
                            "before the bag existed)")
    export.add_argument("run", nargs="?", help="a run directory or its recording.rrd (default: the latest run under "
                        "--runs)")
    export.add_argument("--runs", default="runs", help="where runs are, for the latest (default: runs)")
    export.add_argument("--to", choices=["mcap", "csv"], required=True, help="mcap: a rosbag2 directory of ROS 2 "
                        "messages rebuilt from the rows; csv: one file per entity and component")
    export.add_argument("--out", help="output directory (default: <run>/export-mcap or <run>/export-csv)")
    export.set_defaults(func=_lazy("hilsim.tools.recording.export", "cmd_export"))

    goal = sub.add_parser("goal", help="send a move goal to a running planner and print feedback")
    goal.add_argument("robot", help="the robot's name (its namespace), e.g. arm")
    g = goal.add_mutually_exclusive_group(required=True)
    g.add_argument("--joints", type=float, nargs="+", help="a joint-space target, one value per joint [rad "
                   "or m]")
    g.add_argument("--pose", type=float, nargs="+", help="a tool pose: x y z [m] [roll pitch yaw [rad]]")
    g.add_argument("--xy", type=float, nargs=2, metavar=("X", "Y"), help="a mobile robot's goal [m] (the "
                   "navigator)")
    goal.add_argument("--yaw", type=float, help="with --xy: the final heading [rad]")
    goal.add_argument("--planner", default="", help="a planner by name, e.g. rrtconnect (docs/planning.md; "
                      "default: the scenario's planner.planner)")
    goal.add_argument("--timeout", type=float, default=60.0, help="wall seconds to wait for the result "
                      "(default 60)")
    _endpoint_args(goal)
    goal.set_defaults(func=_lazy("hilsim.planning.client", "cmd_goal"))

    gains = sub.add_parser("gains", help="list the controller gains of a running simulation, or change them live "
                           "(old -> new)")
    gains.add_argument("robot", help="the robot's name (its namespace), e.g. arm")
    gains.add_argument("assignments", nargs="*", metavar="JOINT.GAIN=VALUE", help="e.g. joint_2.kp=80 joint_2.kd=4 "
                       "(gains: kp, ki, kd, i_limit, output_limit, feedforward); none: list the gains")
    _endpoint_args(gains)
    gains.set_defaults(func=_lazy("hilsim.tools.inspection.params", "cmd_gains"))

    plan = sub.add_parser("plan", help="planning evaluation and the learned choice")
    psub = plan.add_subparsers(dest="plan_cmd", required=True)
    ev = psub.add_parser("evaluate", help="plan several targets and compare them (paper Table III)")
    ev.add_argument("--targets", help="targets YAML (required for the arm; a rover scenario: default its task's goals)")
    ev.add_argument("--criterion", choices=get_args(Criterion), default=DEFAULT_CRITERION,
                    help="which plan is best: the shortest, the smoothest, or both weighted "
                    f"(default {DEFAULT_CRITERION})")
    ev.add_argument("--scenario", default="arm", help="the scenario whose robot and world are planned in "
                    "(default arm)")
    ev.add_argument("--csv", help="CSV path; the recording goes next to it (default: OUT/plan_evaluate.csv)")
    ev.add_argument("--out", help="output directory (default runs/<timestamp>-plan-evaluate)")
    ev.add_argument("--execute", action="store_true", help="then run the best plan on a running system")
    ev.add_argument("--scenes", help="a scenes file (config/scenes/scenes.yaml's format): every query with every "
                    "planner of --planners, compared (instead of --targets)")
    ev.add_argument("--planners", help="with --scenes: comma-separated library names, and auto (the learned "
                    "choice) and oracle (each query's best of the others); default every planner, auto and oracle")
    ev.add_argument("--seeds", type=int, default=3, help="with --scenes: runs per query and planner (default 3)")
    ev.add_argument("--strict", action="store_true", help="with --scenes: refuse scenes or queries the choice's "
                    "model was trained on (default: a warning)")
    ev.add_argument("--jobs", type=int, help="with --scenes: worker processes (default: every core)")
    ev.add_argument("--json", action="store_true", help="with --scenes: the figures as one JSON object, last line")
    ev.add_argument("--runs", help="with --scenes: keep every run in this CSV, and take the library planners' runs "
                    "already there from it (resumable)")
    ev.set_defaults(func=_lazy("hilsim.tools.planning_eval.evaluate", "cmd_evaluate"))
    le = psub.add_parser("learn", help="the planner choice (planner: auto): a data set of planner runs, its model")
    le.add_argument("--out", default="models/planner_choice",
                    help="directory (default models/planner_choice: what planner: auto loads)")
    le.add_argument("--seed", type=int, default=0, help="scenes, queries, split and model (default 0)")
    le.add_argument("--scenes", type=int, default=18, help="random scenes besides the shipped ones (default 18)")
    le.add_argument("--queries", type=int, default=6, help="sampled queries per scene (default 6)")
    le.add_argument("--seeds", type=int, default=3, help="runs of each planner on each query (default 3)")
    le.add_argument("--scenario", help="the arm: a scenario file or name (default: the built-in arm); another "
                    "arm's scenes are its world with obstacles sized to its reach, and its model needs its own --out")
    le.add_argument("--planners", help="comma-separated (default: the library's, auto aside)")
    le.add_argument("--iterations", type=int, help="iteration budget per run (default: the library's)")
    le.add_argument("--jobs", type=int, help="worker processes (default: every core)")
    le.add_argument("--train-only", action="store_true", help="only the model, from OUT/data.csv as it is")
    le.set_defaults(func=_lazy("hilsim.tools.planning_eval.learn", "cmd_learn"))
    sc = psub.add_parser("scenes", help="random planning scenes with sampled queries (a scenes file)")
    sc.add_argument("--out", required=True, help="directory: DIR/scenes.yaml and DIR/scenes/*.xml")
    sc.add_argument("--count", type=int, default=12, help="scenes (default 12)")
    sc.add_argument("--seed", type=int, default=1000, help="default 1000 (plan learn's scenes use --seed 0)")
    sc.add_argument("--queries", type=int, default=6, help="queries per scene (default 6)")
    sc.add_argument("--prefix", default="gen", help="scene names: PREFIX<seed>_<k>_<kind> (default gen)")
    sc.add_argument("--scenario", help="the arm: a scenario file or name (default: the built-in arm)")
    sc.set_defaults(func=_lazy("hilsim.tools.planning_eval.learn", "cmd_scenes"))

    bench = sub.add_parser("bench", help="benchmarks (figures and ratios against an in-run baseline)")
    bsub = bench.add_subparsers(dest="bench_cmd", required=True)
    bl = bsub.add_parser("loop", help="distributed lockstep loop vs in-process, and realtime jitter")
    bl.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    bl.add_argument("--sim-seconds", type=float, default=5.0, help="sim seconds of each lockstep run (default 5)")
    bl.add_argument("--realtime-seconds", type=float, default=60.0, help="wall seconds of the realtime run "
                    "(default 60; 0: none)")
    bl.add_argument("--live", type=int, default=0, metavar="N",
                    help="only what watching it live costs: the pipelined arm without --view, with it and nobody "
                         "watching, streaming from the start, with Rerun's viewer joined, and with Foxglove's server "
                         "alone and watched, N rounds (docs/performance.md)")
    bl.add_argument("--identities", type=int, default=0, metavar="N",
                    help="only this: N pairs of runs through the run's router, one identity for every process vs "
                         "one per process (docs/performance.md, \"Identities\")")
    bl.set_defaults(func=_lazy("hilsim.tools.bench.pipeline", "cmd_loop"))
    bsc = bsub.add_parser("scale", help="many robots: real-time factor, step latency, recorder load vs one robot")
    bsc.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    bsc.add_argument("--robots", type=_lazy_ints, default=[1, 2, 4, 8], metavar="N,…",
                     help="numbers of robots to run (must include 1, the baseline; default 1,2,4,8)")
    bsc.add_argument("--subscribers", type=_lazy_ints, default=[0, 4], metavar="S,…",
                     help="numbers of extra plain Zenoh subscribers on the joint_states keys (default 0,4)")
    bsc.add_argument("--sim-seconds", type=float, default=2.0, help="sim seconds per run")
    bsc.add_argument("--compose", action="store_true", help="physics, sensors and controller in one process")
    bsc.add_argument("--repeat", type=int, default=1, help="runs of each configuration, interleaved; the best is kept")
    bsc.add_argument("--arrays", choices=["scenario", "on", "off", "both"], default="scenario",
                     help="fleet.arrays (robots as arrays): as the scenario says, on, off, or both side by side")
    bsc.add_argument("--batch", type=int, default=None, metavar="N",
                     help="logger.batch: samples per batch the services send the recorder (0: off; default: "
                     "as the scenario says)")
    bsc.add_argument("--lag", type=int, choices=[0, 1], default=None,
                     help="clock.controller_lag (default: as config/arm.yaml ships it)")
    bsc.set_defaults(func=_lazy("hilsim.tools.bench.scale", "cmd_scale"))
    bls = bsub.add_parser("loss", help="realtime runs side by side: the share of the samples each recording "
                          "missed, against one run alone (docs/performance.md)")
    bls.add_argument("--runs", type=int, default=2, help="runs at once (default 2)")
    bls.add_argument("--repeat", type=int, default=3, help="rounds, each one run alone then the runs at once "
                     "(default 3)")
    bls.add_argument("--seconds", type=float, default=20.0, help="--duration of each run, seconds (default 20)")
    bls.add_argument("--scenario", default="arm", help="the scenario the runs start (default arm)")
    bls.add_argument("--keep", metavar="DIR", help="keep the run directories under DIR (default: a temporary one)")
    bls.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    bls.set_defaults(func=_lazy("hilsim.tools.bench.loss", "cmd_loss"))
    bc = bsub.add_parser("can", help="CAN bridge: frames per second and added latency vs python-can alone")
    bc.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    bc.add_argument("--samples", type=int, default=1000, help="paced latency probes per path")
    bc.add_argument("--seconds", type=float, default=3.0, help="flat-out duration per direction")
    bc.add_argument("--port", type=int, default=None, help="udp_multicast port (default: a random one)")
    bc.add_argument("--realtime-priority", type=int, default=0, metavar="N",
                    help="run the bridge with bridge-can.realtime_priority N (SCHED_FIFO, as a HIL rig would; "
                         "needs root or CAP_SYS_NICE; default 0: none)")
    bc.set_defaults(func=_lazy("hilsim.bridges.can_bench", "cmd_can"))
    bm = bsub.add_parser("mavlink", help="MAVLink bridge: added latency GPS message -> Zenoh sample vs pymavlink alone")
    bm.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    bm.add_argument("--samples", type=int, default=1000, help="paced latency probes per path")
    bm.add_argument("--seconds", type=float, default=3.0, help="flat-out duration")
    bm.set_defaults(func=_lazy("hilsim.bridges.mavlink_bench", "cmd_mavlink"))
    bp = bsub.add_parser("plan", help="planners on the shipped scenes")
    bp.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    bp.add_argument("--seeds", type=int, default=10, help="runs of each planner on each query (default 10)")
    bp.add_argument("--no-equal-time", action="store_true", help="skip the equal-wall-time pass")
    bp.add_argument("--choice", action="store_true", help="only planner: auto's model load and decision time "
                    "(= hilsim bench choice)")
    bp.add_argument("--scenario", help="the arm: a scenario file or name (default: the built-in arm on the shipped "
                    "scenes); another arm: --scenes")
    bp.add_argument("--scenes", help="a scenes file to plan in (default config/scenes/scenes.yaml)")
    bp.set_defaults(func=_lazy("hilsim.planning.bench", "cmd_bench"))
    bch = bsub.add_parser("choice", help="planner: auto: the model's load and the decision's time (p50/p95/p99) "
                          "on the held-out queries, against its 5 ms bound")
    bch.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    bch.add_argument("--scenes", help="queries to decide on (default models/planner_choice/heldout/scenes.yaml)")
    bch.add_argument("--repeat", type=int, default=5, help="decisions per query (default 5)")
    bch.add_argument("--scenario", default="arm", help="the scenario whose library's auto decides (default arm)")
    bch.set_defaults(func=_lazy("hilsim.planning.bench", "cmd_choice"))
    b2 = bsub.add_parser("ros2", help="the ROS 2 bridge's DDS writes: Cyclone DDS (bridge-ros2-dds) vs rclpy")
    b2.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    b2.add_argument("--count", type=int, default=5000, help="samples per writer")
    b2.add_argument("--rate", type=float, default=1000.0, help="samples per second")
    b2.add_argument("--repeat", type=int, default=3, help="passes of each writer, interleaved (the best is kept)")
    b2.add_argument("--python", default=".venv-ros2/kilted/bin/python",
                    help="a ROS 2 Python with rclpy (default: .venv-ros2/kilted, made by scripts/ros2-venvs.sh)")
    b2.add_argument("--inside", action="store_true", help=argparse.SUPPRESS)
    b2.set_defaults(func=_lazy("hilsim.tools.bench.ros2", "cmd_ros2"))
    br = bsub.add_parser("rover", help="the rover scenario with navigation: lockstep real-time factor, laser rays/s")
    br.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    br.add_argument("--sim-seconds", type=float, default=20.0, help="sim seconds of each run (default 20)")
    br.add_argument("--world", default="indoor", help="indoor or outdoor")
    br.add_argument("--repeat", type=int, default=3, help="runs with the laser on and off each (the best is kept)")
    br.set_defaults(func=_lazy("hilsim.tools.bench.rover", "cmd_rover"))

    inertia = sub.add_parser("inertia", help="a link's mass, centre of mass and inertia tensor from primitives")
    inertia.add_argument("file", help="YAML: links and their parts (box, cylinder, hollow_cylinder, "
                         "thin_square_column, sphere, point), see docs/tools.md")
    inertia.add_argument("--link", help="only this link of the file")
    inertia.add_argument("--urdf", help="write the link's <inertial> into this URDF (needs one link)")
    inertia.add_argument("--json", action="store_true", help="print one JSON object")
    inertia.set_defaults(func=_lazy("hilsim.tools.tuning.inertia", "cmd_inertia"))

    tune = sub.add_parser("tune", help="tune a joint's PID on the real services (Ziegler–Nichols or relay, "
                          "then a refinement that removes overshoot)")
    tune.add_argument("robot", help="scenario name in config/ (e.g. arm) or a YAML path")
    tune.add_argument("joint", nargs="?", help="the joint (or --all); the rover: steering or traction")
    tune.add_argument("--all", action="store_true", help="tune every joint in turn")
    tune.add_argument("--method", choices=["ziegler-nichols", "relay"], default="relay", help="how the ultimate point "
                      "is found: relay (a relay's limit cycle) or ziegler-nichols (proportional gain doubled until "
                      "the oscillation is sustained); default relay (docs/tools.md)")
    tune.add_argument("--step", type=float, help="step of the reference the refinement uses (default 0.2 rad; "
                      "the rover's traction: 2.0 rad/s)")
    tune.add_argument("--measure", type=float, default=1.0, help="sim seconds recorded after each step")
    tune.add_argument("--rise", type=float, help="target rise time [s] (default: the paper's Table II row)")
    tune.add_argument("--settling", type=float, help="target settling time [s] (default: the paper's row)")
    tune.add_argument("--margin", type=float, default=0.8, help="aim at rise and settling this fraction of the "
                      "target (default 0.8): the least gain that does is chosen")
    tune.add_argument("--write", action="store_true", help="write the gains into the scenario file")
    tune.add_argument("--json", action="store_true", help="print one JSON object")
    tune.set_defaults(func=_lazy("hilsim.tools.tuning.autotune", "cmd_tune"))

    robot = sub.add_parser("robot", help="bring a lab's own arm in from its URDF (docs/robots.md)")
    rosub = robot.add_subparsers(dest="robot_cmd", required=True)
    ri = rosub.add_parser("import", help="URDF -> an MJCF with motors, a world, home and targets, tuned gains and "
                          "a scenario that `hilsim up` runs")
    ri.add_argument("urdf", help="the robot's URDF (a xacro must be expanded first: xacro FILE > robot.urdf)")
    ri.add_argument("--package-path", action="append", metavar="DIR",
                    help="a folder holding ROS packages, for package:// mesh URIs (repeatable; also searched: "
                    "ROS_PACKAGE_PATH, and share/ of each AMENT_PREFIX_PATH prefix)")
    ri.add_argument("--name", help="the robot's name: its scenario, files and key namespace (default: the URDF's "
                    "<robot name>)")
    ri.add_argument("--out", help="the folder to write (default: robots/NAME); refused if not empty, unless --force")
    ri.add_argument("--tool", metavar="LINK", help="the link the tool site goes on (default: the SRDF's end "
                    "effector, else the last link of the chain)")
    ri.add_argument("--srdf", help="a MoveIt SRDF (default: one in the package's srdf/ folder naming the same robot)")
    ri.add_argument("--no-tune", action="store_true", help="model-based PD gains instead of tuning each joint "
                    "on the real services (tuning takes about 20 s a joint)")
    ri.add_argument("--seed", type=int, default=0, help="seed of the sampled poses (collision matrix, home search, "
                    "targets; default 0)")
    ri.add_argument("--force", action="store_true", help="replace --out if it holds files")
    ri.set_defaults(func=_lazy("hilsim.tools.robot", "cmd_robot_import"))

    report = sub.add_parser("report", help="measured reports (the arm paper's Table II; the rover's loops)")
    rsub = report.add_subparsers(dest="report_cmd", required=True)
    rs = rsub.add_parser("step", help="step response per joint (the rover: per steering and traction loop) by "
                         "the real services in lockstep (Table II)")
    rs.add_argument("robot", help="scenario name in config/ (e.g. arm, rover) or a YAML path")
    rs.add_argument("--joints", help="comma-separated (default: the built-in arm's joint_1..joint_5, the paper's "
                    "Table II; another arm: every joint; the rover: steering,traction, every wheel's loops; or one "
                    "loop, e.g. fl_steering)")
    rs.add_argument("--step", type=float, default=0.2, help="step of the reference [rad] (default 0.2; the rover: "
                    "of its steering angles)")
    rs.add_argument("--speed", type=float, default=2.0, help="the rover's traction step [rad/s of wheel speed] "
                    "(default 2.0)")
    rs.add_argument("--measure", type=float, default=1.5, help="sim seconds recorded after each step")
    rs.add_argument("--settle", type=float, default=1.0, help="sim seconds back home between steps")
    rs.add_argument("--out", help="output directory (default runs/<timestamp>-step-report)")
    rs.add_argument("--json", action="store_true", help="print one JSON object")
    rs.add_argument("--hil", action="append", default=[], metavar="FILE",
                    help="merge a file over the scenario (e.g. config/hil/can-emulated.yaml): hardware in the loop, "
                    "realtime, a drive's joint measured on its encoder")
    rs.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="override any scenario field")
    rs.set_defaults(func=_lazy("hilsim.tools.tuning.step_report", "cmd_report_step"))

    ident = sub.add_parser("identify", help="fit a real drive's response from a HIL run and write a twin that "
                           "responds the same (docs/hil.md)")
    ident.add_argument("scenario", help="a scenario with the joints served by hardware (e.g. "
                       "config/hil/arm-can-emulated.yaml), or a past HIL run's directory (its bag is fitted)")
    ident.add_argument("--joints", required=True, help="comma-separated joints to identify, e.g. joint_1")
    ident.add_argument("--write", metavar="FILE", help="write the twin scenario here (default: <out>/twin.yaml; a run "
                       "directory: only when given)")
    ident.add_argument("--json", action="store_true", help="print one JSON object: the fits and the comparisons")
    ident.add_argument("--hil", action="append", default=[], metavar="FILE", help="merge a file over the scenario")
    ident.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="override any scenario field")
    ident.add_argument("--scale", type=float, default=1.0, help="the excitation's size (1: steps up to 1.7 rad)")
    ident.add_argument("--measure", type=float, default=1.0, help="sim seconds each validation step is measured "
                       "(a slow drive needs more to settle)")
    ident.add_argument("--out", help="output directory (default runs/<timestamp>-identify)")
    ident.set_defaults(func=_lazy("hilsim.tools.tuning.identify", "cmd_identify"))

    comp = sub.add_parser("compose", help="write the docker compose file of a scenario and its HIL variants")
    comp.add_argument("scenario", help="scenario name in config/ (e.g. arm) or a YAML path")
    comp.add_argument("--hil", action="append", default=[], metavar="FILE",
                      help="a HIL scenario (e.g. config/hil/arm-can.yaml): its bridges become a profile; repeatable")
    comp.add_argument("--out", help="write here (default: standard output)")
    comp.set_defaults(func=_lazy("hilsim.launch.deploy", "cmd_compose"))

    router = sub.add_parser("router", help="run a standalone Zenoh router (loopback unless told otherwise)")
    router.add_argument("--listen", help="endpoint to listen on (default tcp/127.0.0.1:7447; with --config, "
                        "replaces the file's)")
    router.add_argument("--config", help="a Zenoh router config file (JSON5: listen endpoints, TLS, access "
                        "control), e.g. config/security/router.json5")
    router.set_defaults(func=_lazy("hilsim.launch.launcher", "cmd_router"))

    creds = sub.add_parser("creds", help="identities a lab hands out: one node or tool, only the rights given "
                           "(docs/security.md)")
    csub = creds.add_subparsers(dest="creds_cmd", required=True)
    cadd = csub.add_parser("add", help="write a credential (a Zenoh client config) that runs started afterwards admit")
    cadd.add_argument("name")
    cadd.add_argument("--may-write", metavar="TOPIC[,…]", help="topics it may put, of what a person commands "
                      "(cmd_vel, joint_trajectory)")
    cadd.add_argument("--may-ask", metavar="NAME[,…]", help="queryables it may ask (planner/goal, planner/cancel, "
                      "controller/set_parameters, …; actions: the services' ROS 2 actions)")
    cadd.add_argument("--read-only", action="store_true", help="it reads, nothing else")
    cadd.add_argument("--connect", default="tcp/127.0.0.1:7447", help="the router its config names")
    csub.add_parser("list", help="the lab's credentials and what each may do")
    crm = csub.add_parser("rm", help="remove a credential (runs started afterwards no longer admit it)")
    crm.add_argument("name")
    creds.set_defaults(func=_lazy("hilsim.launch.creds", "cmd_creds"))

    ui = sub.add_parser("ui", help="the browser control panel: choose, start, command and watch a run")
    ui.add_argument("--host", default="127.0.0.1", help="address to listen on (default loopback; anyone who "
                    "reaches it needs the token)")
    ui.add_argument("--no-token", action="store_true", help="serve without a token (docs/panel.md): any "
                    "process or user of this machine that reaches the port may command the robot")
    ui.add_argument("--port", type=int, default=8080, help="HTTP port (default 8080)")
    ui.add_argument("--connect", help="join this Zenoh router instead of opening one (runs started from the "
                    "panel use it too)")
    ui.add_argument("--run", metavar="DIR", help="join the run of yours that is up in DIR (its router)")
    ui.add_argument("--prefix", default=None, help="key prefix (default: HILSIM_PREFIX, else hilsim)")
    ui.set_defaults(func=_lazy("hilsim.ui.server", "cmd_ui"))
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except ConnectionError as e:  # a tool that reaches nothing (hilsim.core.run_finder.open_tool_session): no run up,
        print(f"error: {str(e).splitlines()[0]}", file=sys.stderr)  # the same mistake, the same code in every tool
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
