"""The scenario schema: what a scenario file may say, validated with pydantic.

Only the schema lives here (and :class:`ConfigError`, :func:`format_error`, the one-line error of
a bad field). Reading files, ``extends:``, overrides and the environment is
:mod:`hilsim.core.scenario`; which robots a scenario has and what its services are called,
:mod:`hilsim.core.fleet` (below this module). Checks that need the registry of services get its
names through pydantic's validation context, which the loader supplies.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator, model_validator

from hilsim.core import fleet

REPO_ROOT = Path(__file__).resolve().parents[2]
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


class ConfigError(Exception):
    """A scenario that cannot be used; the message is one line for the user."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class TlsConfig(_Model):
    """This process's TLS identity (docs/security.md): the CA that signed the router's
    certificate, and this process's own certificate and key, which the router checks (mTLS) and
    whose common name its access control knows. Paths are absolute or relative to the current
    directory."""

    root_ca: Path = Field(description="PEM of the certificate authority")
    certificate: Path = Field(description="PEM of this process's certificate (signed by root_ca)")
    private_key: Path = Field(description="PEM of its private key")

    @model_validator(mode="after")
    def _files_exist(self) -> TlsConfig:
        for name in ("root_ca", "certificate", "private_key"):
            f = getattr(self, name)
            if not f.is_file():
                raise ValueError(f"{name}: file {f} does not exist (scripts/make-certs.sh makes a throw-away set)")
        return self


class ZenohConfig(_Model):
    mode: Literal["peer", "client"] = "peer"
    # Where the services meet. `hilsim up` runs a router on loopback and fills this in.
    connect: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:0"])
    multicast_scouting: bool = False
    # None: plain TCP (the loopback default). Set: TLS to the router with this identity; the
    # process is then a client of the router (no listener of its own, so nothing reaches it
    # without passing the router's certificate check and access control)
    tls: TlsConfig | None = None
    # None: no Zenoh user/password. Set: a Zenoh client config file holding them
    # (transport.auth.usrpwd), e.g. the zenoh-client.json5 that `hilsim up` writes for its run
    # (docs/security.md); `hilsim up` sets it for its own services
    auth: Path | None = Field(None, description="Zenoh config file with transport.auth.usrpwd user and password "
                              "(hilsim up writes <run dir>/zenoh-client.json5 and fills this in)")
    guests: Literal["none", "read"] = Field(
        "none", description="hilsim up's router: whether a process with the run's guest credentials "
        "(<run dir>/zenoh-guest.json5) may read every key (read) or nobody but the run's own processes may "
        "connect (none)")


class ClockConfig(_Model):
    mode: Literal["lockstep", "realtime"] = "lockstep"
    dt: float = Field(0.001, gt=0, le=0.1, description="physics step [s]")
    ack_timeout: float = Field(
        30.0, gt=0, description="wall seconds physics waits for a lockstep ack before the run is stalled "
        "(longer than the planner's wall-clock cap on one plan, which a lockstep step may include)",
    )
    max_age: float = Field(
        0.05, ge=0, description="realtime: a received sample older than this (wall seconds since it was sent) is "
        "dropped as stale and counted, so a service that fell behind catches up (streams only: a trajectory, "
        "given once, is never dropped); 0 = keep every sample",
    )
    controller_lag: int = Field(
        0, ge=0, le=1, description="lockstep: steps between the measurement a controller's command answers and the "
        "step it acts on; 1 models the one-sample computation delay of a digital controller and lets physics, "
        "sensors and controller work on neighbouring steps at once (docs/keys.md, docs/performance.md)",
    )
    start_delay: float = Field(
        0.5, ge=0, description="wall seconds between every service being live and step 0 (peers finish connecting)"
    )
    start_timeout: float = Field(
        120.0, gt=0, description="wall seconds hilsim up and physics wait for every service to announce itself "
        "before the run fails (hilsim up --wait sets it)",
    )


class WorldConfig(_Model):
    model: Path = Field(description="MJCF world file (robot included)")
    urdf: Path | None = None
    home: list[float] | None = Field(None, description="the pose physics starts in, one value per actuated joint "
                                     "(default: the model's keyframe 'home' if it has one, else its zero pose)")


Interface = Literal["effort", "position", "velocity"]


class DriveConfig(_Model):
    """A servo drive simulated in lockstep (:mod:`hilsim.sim.drive`): its closed-loop response from
    setpoint to encoder, as ``hilsim identify`` fits it from a real drive (docs/hil.md)."""

    order: Literal[1, 2] = Field(2, description="1: position lag time_constant; 2: natural_frequency, damping_ratio")
    dead_time: float = Field(0.0, ge=0, le=1.0, description="[s] from the setpoint's stamp to the drive acting on it")
    natural_frequency: float = Field(40.0, gt=0, description="order 2: ω_n of the closed loop [rad/s]")
    damping_ratio: float = Field(1.0, gt=0, description="order 2: ζ")
    time_constant: float = Field(0.02, gt=0, description="order 1: τ [s]")
    max_velocity: float = Field(math.inf, gt=0, description="[rad/s] (inf: none)")
    max_acceleration: float = Field(math.inf, gt=0, description="[rad/s²] (inf: none)")
    resolution: float = Field(0.0, ge=0, description="the encoder's quantum [rad] (0: exact)")
    period: float = Field(0.0, ge=0, le=1.0, description="[s] between the encoder's reports (0: every physics step)")


class JointConfig(_Model):
    """How one joint is commanded and who serves it (like a ros2_control hardware interface)."""

    interface: Interface = Field("effort", description="command interface: effort, position or velocity")
    server: str = Field(SIM, description="'sim' (physics) or the name of an external server (e.g. motor-model)")
    servo_kp: float | None = Field(None, gt=0, description="simulated drive: position [N·m/rad] or velocity "
                                   "[N·m·s/rad] servo gain (default 100 / 10)")
    servo_kv: float | None = Field(None, ge=0, description="simulated position drive: damping [N·m·s/rad] (default 5)")
    drive: DriveConfig | None = Field(None, description="a position or velocity joint simulated by physics as this "
                                      "drive (hilsim.sim.drive: dead time, closed loop, limits, encoder) instead of "
                                      "MuJoCo's servo; what hilsim identify writes for a twin")


class PhysicsConfig(_Model):
    truth_imu_site: str | None = "imu"
    gravity_compensation: list[str] = Field(
        default_factory=list, description="bodies whose gravity is compensated (names or glob patterns, e.g. 'link_*')"
    )
    follow_extrapolation: float = Field(
        0.0, ge=0, le=0.1, description="external joints: carry a server's last report forward at its velocity for "
        "at most this many seconds (e.g. one report period of a drive that reports every 10 ms); 0 = hold it",
    )
    server_timeout: float = Field(
        0.25, gt=0, description="wall seconds without state from an external joint server before it is a fault"
    )
    tf_rate_hz: float = Field(50.0, ge=0, description="/tf of the URDF's moving joints (0: off)")


class SensorConfig(BaseModel):
    """One emulated sensor; ``type`` picks the class, the other fields are its parameters."""

    model_config = ConfigDict(extra="allow")
    type: str
    rate_hz: float = Field(100.0, gt=0)
    enabled: bool = True


class PidGains(_Model):
    kp: float = Field(ge=0)
    ki: float = Field(0.0, ge=0)
    kd: float = Field(0.0, ge=0)
    i_limit: float = Field(math.inf, gt=0, description="anti-windup: limit on |ki * integral|")
    output_limit: float | None = Field(None, gt=0)
    feedforward: float = Field(0.0, ge=0, description="velocity feed-forward gain")


class ControllerConfig(_Model):
    type: str = Field("joint_trajectory", description="control law, by name (built-in or hilsim.controllers plug-in)")
    rate_hz: float = Field(1000.0, gt=0)
    velocity_gain: float = Field(
        10.0, ge=0, description="velocity-interface joints: command = v_ref + velocity_gain·(p_ref − p) [1/s]"
    )
    gains: dict[str, PidGains] = Field(default_factory=dict, description="per joint name, or 'default'")
    hold_timeout: float = Field(0.05, gt=0, description="sim seconds without joint_states before holding")
    params: dict[str, Any] = Field(
        default_factory=dict, description="settings of the control law named by `type`, validated by its class "
        "(e.g. four_wheel_steer: max_speed, cmd_timeout, script)",
    )


# the planner's criterion (hilsim.planning.scoring computes it): the names, and what auto chooses for by default
Criterion = Literal["length", "smoothness", "weighted"]
DEFAULT_CRITERION: Criterion = "weighted"


class PlannerConfig(_Model):
    planner: str = Field("improved_rrtstar", description="default planner, by name in the planner library (the "
                         "paper's improved RRT*; RRT-Connect's path when it finds none: ±2π and continuous joints)")
    planning_time: float = Field(1.0, gt=0, description="wall seconds per plan (realtime)")
    clearance: float = Field(0.005, ge=0, description="minimum distance to obstacles [m]")
    rate_hz: float = Field(100.0, gt=0, description="how often the planner decides (starts goals, monitors)")
    library: Path | None = Field(None, description="planner library YAML (default config/planners.yaml)")
    iterations: int | None = Field(
        None, gt=0, description="iteration budget per plan: lockstep default the library's; in realtime "
        "only when set, and planning_time still caps it"
    )
    criterion: Criterion = Field(
        DEFAULT_CRITERION, description="what planner: auto chooses for: hilsim plan evaluate's criterion "
        "(joint path length, acceleration variance, or both), plus planning time"
    )


class TaskConfig(_Model):
    targets: list[list[float]] = Field(default_factory=list)
    tolerance: float = Field(0.01, gt=0)
    settle_time: float = Field(0.3, ge=0)
    target_timeout: float = Field(30.0, gt=0, description="sim seconds per target")


class LiveConfig(_Model):
    """The recorder's live stream to Rerun's web viewer (``hilsim up --view``; hilsim.record.live)."""

    enabled: bool = Field(False, description="stream the recording live to Rerun's bundled web viewer while the run "
                          "goes on (the address in <run dir>/live.json; docs/recording.md, \"Watch it live\")")
    host: str = Field("127.0.0.1", description="the address the viewer listens on (loopback; another one asks a "
                      "token in the viewer's URL)")
    port: int = Field(0, ge=0, le=65535, description="the viewer page's port (0: a free one)")


class FoxgloveConfig(_Model):
    """The recorder's samples on a Foxglove WebSocket server (``hilsim up --foxglove``; hilsim.record.foxglove_live)."""

    enabled: bool = Field(False, description="serve every recorded key's samples (raw CDR, ros2msg schemas) over "
                          "Foxglove's WebSocket protocol while the run goes on")
    host: str = Field("127.0.0.1", description="the address the server listens on (loopback)")
    port: int = Field(8765, ge=0, le=65535, description="its port (0: a free one)")


class LoggerConfig(_Model):
    enabled: bool = Field(True, description="false: no recorder in the run (as `hilsim up --no-logger`)")
    out_dir: Path = Path("runs")
    run_dir: Path | None = Field(None, description="write here instead of <out_dir>/<timestamp> (set by `hilsim up`)")
    record: list[str] = Field(default_factory=lambda: ["**"],
                              description="key expressions under <domain id>/, e.g. arm/** (hilsim.core.keys)")
    bag: bool = Field(True, description="also write <run dir>/bag/, a rosbag2 bag (MCAP) of every sample's raw CDR "
                      "(docs/recording.md)")
    batch: int = Field(256, ge=0, le=65535, description="samples per batch the run's services send the recorder on "
                       "one key each instead of every sample on its own key; writers outside them (ROS 2 nodes, "
                       "tools, bridges of other runs) are subscribed key by key from their publisher tokens (0: off, "
                       "the recorder subscribes to every key; docs/recording.md)")
    batch_max_age_ms: float = Field(50.0, gt=0, le=10_000, description="a batch not full is sent when its first "
                                    "sample is this old (wall ms), so a slow key's samples do not wait")
    max_bag_size: int = Field(0, ge=0, description="split the bag: a new file once the current one holds this many "
                              "bytes (as rosbag2's --max-bag-size; 0: no split by size; also '500MB', '2GiB')")
    max_bag_duration: float = Field(0.0, ge=0, description="split the bag: a new file once the current one spans "
                                    "this many seconds of receive time (as rosbag2's --max-bag-duration; 0: none)")
    max_rrd_size: int = Field(0, ge=0, description="split the Rerun recording: a new file (recording.part-1.rrd, "
                              "…) once the current one holds this many bytes, checked at each flush (twice a "
                              "second); the files are one recording, opened together by Rerun's viewer (0: no "
                              "split by size; also '500MB'; hilsim up --interactive: 500MB unless set)")
    max_rrd_duration: float = Field(0.0, ge=0, description="split the Rerun recording: a new file once the current "
                                    "one spans this many seconds of wall time (0: none)")
    max_size: int = Field(0, ge=0, description="cap on the run's recording (recording.rrd and bag/ together, "
                          "bytes; '2GB' too): the recorder stops recording there and the run goes on (0: no cap)")
    max_loss: float = Field(0.05, ge=0, le=1, description="realtime: the largest fraction of the published samples "
                            "the recording may miss (lost in transport, dropped by the recorder, never reached it); "
                            "more fails the run, 'result: FAILED (recording lost N %)' (1: never; hilsim up "
                            "--allow-loss). Lockstep loses nothing, whatever this says")
    min_free: int = Field(500 * 1000**2, ge=0, description="the recorder stops recording (the run goes on) before "
                          "the free space of the run directory's file system falls below this many bytes ('1GB' "
                          "too; 0: only a full disk stops it)")
    live: LiveConfig = Field(default_factory=LiveConfig)
    foxglove: FoxgloveConfig = Field(default_factory=FoxgloveConfig)

    @field_validator("max_bag_size", "max_rrd_size", "max_size", "min_free", mode="before")
    @classmethod
    def _bytes(cls, v: Any) -> Any:
        return parse_bytes(v) if isinstance(v, str) else v


class Ros2Config(_Model):
    """Where the simulation sits in the ROS 2 graph (rmw_zenoh's key scheme: docs/ros2.md)."""

    domain_id: int = Field(0, ge=0, le=232, description="ROS_DOMAIN_ID of every key; two simulations on one "
                           "router use different ones")
    namespace: str = Field("/{robot}", description="a robot's namespace, {robot} replaced by its name")
    enclave: str = Field("/", description="the enclave of hilsim's nodes in their graph tokens")

    @field_validator("namespace")
    @classmethod
    def _ns(cls, v: str) -> str:
        if not v.startswith("/") or "{robot}" not in v or any(c in v for c in "*?#$ -"):
            raise ValueError("must start with '/', contain {robot} and only ROS 2 name characters, e.g. /{robot}")
        return v


class FleetConfig(_Model):
    """How a fleet (``robots`` > 1) is computed (:mod:`hilsim.core.fleet`)."""

    arrays: bool = Field(True, description="robots > 1: a process serving every robot's sensors or controller "
                         "(sensors@*, controller@*) steps them as numpy arrays and trades one fleet-wide sample per "
                         "step with physics (fleet/truth/joint_states, fleet/joint_states, fleet/joint_commands); "
                         "the per-robot keys are still published for whoever subscribes; robots with encoder or "
                         "control rates of their own run robot by robot (hilsim.core.scenario.array_misfit)")


RestartPolicy = Literal["no", "on-failure"]


class RestartConfig(_Model):
    """What ``hilsim up`` does when a service dies (like compose's ``restart:``): ``no`` (report
    and stop the run) or ``on-failure`` (start it again, at most ``max_attempts`` times per
    service, after ``backoff`` seconds, doubled at each attempt). Physics is never restarted: it
    holds sim time and the robot's true state, which a new process would not have."""

    services: dict[str, RestartPolicy] = Field(
        default_factory=dict, description="per service name, or 'default' for the others: no | on-failure"
    )
    max_attempts: int = Field(3, ge=1, le=100, description="restarts per service and run")
    backoff: float = Field(0.5, ge=0, le=60, description="wall seconds before the first restart (doubled each time)")

    @field_validator("services", mode="before")
    @classmethod
    def _no_is_not_false(cls, v: Any) -> Any:
        # YAML reads a bare `no` as False (compose has the same trap): take it as the policy "no"
        if isinstance(v, dict):
            return {k: "no" if p is False else p for k, p in v.items()}
        return v

    @field_validator("services")
    @classmethod
    def _known(cls, v: dict[str, str], info: ValidationInfo) -> dict[str, str]:
        known = known_services(info)
        for name, policy in v.items():
            if known is not None and name != "default" and name not in known:
                raise ValueError(f"unknown service {name!r}; expected 'default' or one of {', '.join(known)}")
            if name == "physics" and policy != "no":
                raise ValueError("physics cannot be restarted: sim time and the robot's true state would be lost")
        return v

    def policy(self, service: str) -> str:
        """The policy of ``service`` (its own entry, else ``default``, else no); physics: no. A
        composed process ``a+b`` (:mod:`hilsim.run.compose`) is restarted only if each of its members is."""
        if "+" in service:
            return "on-failure" if all(self.policy(s) == "on-failure" for s in service.split("+")) else "no"
        service = service.split("@")[0]  # robots > 1: controller@arm3, controller@* (hilsim.core.fleet)
        if service == "physics":
            return "no"
        return self.services.get(service, self.services.get("default", "no"))


# the navigator's section (services/navigator.py reads it; hilsim plan evaluate on a rover too)
class FootprintConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    length: float = Field(1.0, gt=0, description="m, along x (wheels included)")
    width: float = Field(0.9, gt=0, description="m, along y (wheels included)")
    circles: int = Field(2, ge=1, le=8, description="circles along x that cover the rectangle")


class FollowerConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    max_speed: float = Field(0.6, gt=0, description="m/s")
    min_speed: float = Field(0.06, gt=0, description="m/s while moving")
    max_yaw_rate: float = Field(1.0, gt=0, description="rad/s")
    accel: float = Field(0.4, gt=0, description="m/s², braking profile to cusps and the goal")
    lookahead: float = Field(0.4, gt=0, description="m")
    k_yaw: float = Field(2.0, gt=0, description="1/s")
    k_final: float = Field(1.0, gt=0, description="1/s: speed per metre to the goal")
    xy_tolerance: float = Field(0.06, gt=0, description="m: translation stops this close to the goal")
    yaw_tolerance: float = Field(0.05, gt=0, description="rad: final yaw")
    cusp_tolerance: float = Field(0.1, gt=0, description="m")


class NavigatorConfig(BaseModel):
    """The ``navigator:`` section of a scenario."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    rate_hz: float = Field(20.0, gt=0, description="decision ticks (must divide controller.rate_hz)")
    resolution: float = Field(0.05, gt=0, le=1.0, description="grid cell [m]")
    z_band: tuple[float, float] = Field((0.1, 0.7), description="heights [m] whose geometry is an obstacle")
    bounds: tuple[float, float, float, float] | None = Field(
        None, description="x_min, x_max, y_min, y_max of the map (default: the static geometry + 1 m)")
    footprint: FootprintConfig = Field(default_factory=FootprintConfig)
    clearance: float = Field(0.05, ge=0, description="m added to the footprint's circles")
    turning_radius: float = Field(0.8, gt=0, description="Reeds–Shepp turning radius [m]")
    planner: str = Field("RRTConnect", description="OMPL geometric planner")
    planner_range: float = Field(3.0, gt=0, description="m: the planner's longest tree edge (setRange)")
    attempts: int = Field(3, ge=1, le=20, description="plans per goal; the shortest is followed")
    iterations: int = Field(20000, gt=0, description="iteration budget per plan (deterministic)")
    planning_time: float = Field(5.0, gt=0, description="wall-clock cap per plan [s]")
    goal_tolerance: float = Field(0.1, gt=0, description="m: a goal counts as reached within this (odometry)")
    goal_timeout: float = Field(30.0, gt=0, description="sim s per goal beyond the path's time at max_speed")
    replan_distance: float = Field(0.5, gt=0, description="m off the path before it is planned again")
    max_replans: int = Field(2, ge=0, description="replans per goal (off the path, or stopped short of the goal)")
    map_period: float = Field(5.0, gt=0, description="sim s between map publications")
    follower: FollowerConfig = Field(default_factory=FollowerConfig)

    @model_validator(mode="after")
    def _band(self) -> NavigatorConfig:
        if not self.z_band[1] > self.z_band[0]:
            raise ValueError(f"z_band must be [low, high] with high > low (got {list(self.z_band)})")
        if self.bounds is not None and not (self.bounds[1] > self.bounds[0] and self.bounds[3] > self.bounds[2]):
            raise ValueError(f"bounds must be [x_min, x_max, y_min, y_max] with max > min (got {list(self.bounds)})")
        return self


class Scenario(_Model):
    """A scenario. Besides the fields below, a top-level section named after a service (e.g.
    ``motor-model:``) holds that service's own settings; its class validates them."""

    model_config = ConfigDict(extra="allow", validate_assignment=True)
    name: str
    robot: str = "arm"
    robots: int = Field(1, ge=1, le=64, description="copies of the robot, side by side in one world: "
                        "robots <robot>0 … <robot>N-1, each under its own key namespace (hilsim.core.fleet)")
    robot_spacing: list[float] = Field(
        default_factory=lambda: [0.0, 1.5, 0.0], min_length=3, max_length=3,
        description="robots > 1: offset [m] of each copy of the world model from the previous one",
    )
    robot_overrides: dict[str, dict[str, Any]] = Field(
        default_factory=dict,
        description="robots > 1: per robot (arm0, …), its own settings as dotted fields under "
                    "task, controller, planner or sensors, e.g. {arm1: {task.targets: [[…]]}}",
    )
    prefix: str = "hilsim"
    seed: int = 0
    duration: float | None = Field(None, gt=0, description="sim seconds; None = until the task ends")
    services: list[str] = Field(default_factory=lambda: list(DEFAULT_SERVICES))
    compose: list[list[str]] = Field(
        default_factory=list,
        description="groups of services run in one process each, e.g. [[physics, sensors, controller]]",
    )
    zenoh: ZenohConfig = Field(default_factory=ZenohConfig)
    clock: ClockConfig = Field(default_factory=ClockConfig)
    world: WorldConfig
    physics: PhysicsConfig = Field(default_factory=PhysicsConfig)
    joints: dict[str, JointConfig] = Field(
        default_factory=dict, description="per joint name, or 'default' for the others: interface and server"
    )
    sensors: dict[str, SensorConfig] = Field(default_factory=dict)
    controller: ControllerConfig = Field(default_factory=ControllerConfig)
    planner: PlannerConfig = Field(default_factory=PlannerConfig)
    task: TaskConfig = Field(default_factory=TaskConfig)
    logger: LoggerConfig = Field(default_factory=LoggerConfig)
    ros2: Ros2Config = Field(default_factory=Ros2Config)
    fleet: FleetConfig = Field(default_factory=FleetConfig)
    restart: RestartConfig = Field(default_factory=RestartConfig)
    source: Path | None = Field(None, exclude=True, description="file this came from")
    fleet_member: bool = Field(False, exclude=True, description="set by hilsim.core.fleet: one robot's view of a "
                               "scenario with robots > 1 (its files in the run directory carry its name)")

    @field_validator("prefix", "robot")
    @classmethod
    def _key_safe(cls, v: str) -> str:
        if not v or any(c in v for c in "/*?#$ "):
            raise ValueError("must be a non-empty name without '/', '*', '?', '#', '$' or spaces")
        return v

    @field_validator("services")
    @classmethod
    def _known_services(cls, v: list[str], info: ValidationInfo) -> list[str]:
        known = known_services(info)
        for s in v:
            if known is not None and s not in known:
                raise ValueError(f"unknown service {s!r}; available: {', '.join(known)}")
        if len(set(v)) != len(v):
            raise ValueError("a service is listed twice")
        return v

    @model_validator(mode="after")
    def _recorder_off(self) -> Scenario:
        if not self.logger.enabled and "logger" in self.services:  # the same as `hilsim up --no-logger`
            self.services = [s for s in self.services if s != "logger"]
        return self

    @model_validator(mode="after")
    def _fleet(self) -> Scenario:
        if self.robots > 1 and self.external_servers():
            raise ValueError(f"robots: {self.robots} robots need every joint served by sim "
                             f"(external servers: {', '.join(self.external_servers())})")
        names = fleet.robot_names(self)
        for robot, over in self.robot_overrides.items():
            if self.robots == 1 or robot not in names:
                raise ValueError(f"robot_overrides.{robot}: no such robot (robots: {', '.join(names)}; "
                                 f"overrides need robots > 1)")
            for field in over:
                if field.split(".")[0] not in fleet.OVERRIDABLE:
                    raise ValueError(f"robot_overrides.{robot}.{field}: a robot may change only fields under "
                                     f"{', '.join(fleet.OVERRIDABLE)} (the world and clock are shared)")
        # a bad value in an override is said by the loader (hilsim.core.scenario), which builds each robot's view
        return self

    @model_validator(mode="after")
    def _drives(self) -> Scenario:
        for name in self.joints:
            j = self.joint(name)
            if j.drive is None:
                continue
            if j.server != SIM:
                raise ValueError(f"joints.{name}.drive: a simulated drive is physics' (server: sim), but the joint's "
                                 f"server is {j.server!r}")
            if j.interface == "effort":
                raise ValueError(f"joints.{name}.drive: a simulated drive takes a position or velocity setpoint "
                                 f"(interface: position or velocity), not effort")
        return self

    @model_validator(mode="after")
    def _compose_groups(self) -> Scenario:
        seen: set[str] = set()
        base = self._base_processes()
        for i, g in enumerate(self.compose):
            for s in g:
                if s not in base:
                    raise ValueError(f"compose[{i}]: {s!r} is not one of this scenario's services "
                                     f"({', '.join(base)})")
                if s in seen:
                    raise ValueError(f"compose[{i}]: {s!r} is in two groups")
                seen.add(s)
            if len(g) < 2:
                raise ValueError(f"compose[{i}]: a group needs at least two services, got {g}")
        return self

    @model_validator(mode="after")
    def _service_sections(self, info: ValidationInfo) -> Scenario:
        known = known_services(info)
        if known is None:
            return self
        for k in self.model_extra or {}:
            if k not in known:
                raise ValueError(f"unknown field {k!r} (not a scenario field, nor a service's section; "
                                 f"services: {', '.join(known)})")
        return self

    def joint(self, name: str) -> JointConfig:
        """The interface and server of a joint: the fields its own entry sets, over ``default``'s,
        over effort/sim."""
        base = self.joints.get("default") or JointConfig()
        own = self.joints.get(name)
        if own is None:
            return base
        return base.model_copy(update={f: getattr(own, f) for f in own.model_fields_set})

    def served_by(self, server: str) -> list[str]:
        """The joints ``server`` serves, named one by one in ``joints`` (one-line ConfigError if
        it serves none, or is the server of ``default``: it must know its joints by name)."""
        where = self.source or "scenario"
        if self.joint("default").server == server:
            raise ConfigError(f"{where}: joints.default.server: name the joints {server} serves one by one")
        mine = [n for n in self.joints if n != "default" and self.joint(n).server == server]
        if not mine:
            raise ConfigError(f"{where}: joints: no joint has server: {server}, so {server} has nothing to serve")
        return mine

    def external_servers(self) -> list[str]:
        """External joint servers named in ``joints`` (in order of first mention)."""
        out: list[str] = []
        for j in self.joints.values():
            if j.server != SIM and j.server not in out:
                out.append(j.server)
        return out

    def _base_processes(self) -> list[str]:
        return [*self.services, *(s for s in self.external_servers() if s not in self.services)]

    def processes(self) -> list[str]:
        """Every service this scenario runs: ``services`` plus the external joint servers. With
        ``robots`` > 1, a per-robot service once per robot, as ``<service>@<robot>`` (hilsim.core.fleet)."""
        return fleet.expand_processes(self, self._base_processes())

    def launch_units(self) -> list[str]:
        """The OS processes ``hilsim up`` starts: one per service, except the services of a
        ``compose`` group, which share one named ``a+b+c`` (:mod:`hilsim.run.compose`). With
        ``robots`` > 1, a per-robot service's unit is ``<service>@*``: one process serving every robot."""
        procs = self._base_processes()
        grouped = {s: "+".join(m for m in g if m in procs) for g in self.compose for s in g}
        if self.robots > 1:
            return [fleet.fleet_unit(u) for u in self._units(procs, grouped)]
        return self._units(procs, grouped)

    def _units(self, procs: list[str], grouped: dict[str, str]) -> list[str]:
        out: list[str] = []
        for s in procs:
            unit = grouped.get(s, s)
            if unit not in out:
                out.append(unit)
        return out

    def section(self, name: str) -> dict[str, Any]:
        """Raw settings of a plug-in or server section (validated by the service that owns it)."""
        v = (self.model_extra or {}).get(name, {})
        return v if isinstance(v, dict) else {}

    @model_validator(mode="after")
    def _control_rate(self) -> Scenario:
        steps = 1.0 / (self.controller.rate_hz * self.clock.dt)
        if abs(steps - round(steps)) > 1e-6 or round(steps) < 1:
            raise ValueError(
                f"controller.rate_hz ({self.controller.rate_hz}) must divide "
                f"the physics rate ({1 / self.clock.dt:g} Hz)"
            )
        return self

    @model_validator(mode="after")
    def _planner_rate(self) -> Scenario:
        ratio = self.controller.rate_hz / self.planner.rate_hz
        if abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
            raise ValueError(
                f"planner.rate_hz ({self.planner.rate_hz:g}) must divide controller.rate_hz "
                f"({self.controller.rate_hz:g}): the planner decides on joint_states of its own steps"
            )
        return self

    @property
    def planner_decimation(self) -> int:
        """Physics steps per planner decision (the planner acknowledges only those steps)."""
        return round(1.0 / (self.planner.rate_hz * self.clock.dt))

    def planner_tick(self, t_ns: int) -> bool:
        """Whether the step at sim time ``t_ns`` is one the planner decides on (and the sensors'
        ``joint_states_throttle`` carries)."""
        return (t_ns // self.dt_ns) % self.planner_decimation == 0

    @property
    def dt_ns(self) -> int:
        return round(self.clock.dt * 1e9)

    @property
    def control_decimation(self) -> int:
        return round(1.0 / (self.controller.rate_hz * self.clock.dt))

    def dump(self) -> dict[str, Any]:
        return self.model_dump(mode="json", exclude={"source"})


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


TLS_ENV = {"root_ca": "HILSIM_TLS_ROOT_CA", "certificate": "HILSIM_TLS_CERTIFICATE",
           "private_key": "HILSIM_TLS_PRIVATE_KEY"}


def tls_from_env() -> dict[str, str] | None:
    """``zenoh.tls`` from ``HILSIM_TLS_ROOT_CA``, ``HILSIM_TLS_CERTIFICATE`` and
    ``HILSIM_TLS_PRIVATE_KEY`` (all three, or None when none is set)."""
    got = {k: os.environ.get(v, "") for k, v in TLS_ENV.items()}
    if not any(got.values()):
        return None
    missing = [TLS_ENV[k] for k, v in got.items() if not v]
    if missing:
        raise ConfigError(f"TLS from the environment: {', '.join(missing)} not set (set all three, or none)")
    return got


def require_realtime(sc: Scenario, field: str, why: str, where: str | Path | None = None) -> None:
    """Hardware (a drive, a GPS, an autopilot, an external joint server) lives on the wall clock and cannot wait
    for a lockstep step: a scenario that puts one in lockstep is refused in one line, the same for every kind
    (``field``: the field that brings the hardware in; ``why``: what it is, e.g. ``bridge-mavlink talks to a
    device on the wall clock``)."""
    if sc.clock.mode != "realtime":
        raise ConfigError(f"{where or sc.source or 'scenario'}: {field}: {why}, so the scenario needs clock.mode: "
                          f"realtime (got {sc.clock.mode!r}; pass --clock realtime)")
