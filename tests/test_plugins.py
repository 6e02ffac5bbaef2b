"""The plug-in seam: a package made here, in a temporary directory, and installed (a real wheel,
with its entry points) adds a sensor kind and a service, and a scenario uses both, with no file
of hilsim changed.

The package is installed with ``pip install --target`` into a directory of the test, never into
the test venv: the in-process test puts that directory on ``sys.path`` for its duration, the
end-to-end test puts it on ``PYTHONPATH`` of ``hilsim up``, whose services inherit it.
"""

from __future__ import annotations

import base64
import hashlib
import importlib
import importlib.metadata
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from hilsim.core import keys as hilsim_keys
from hilsim.core import msgs, registry, transport
from hilsim.core.config import ZenohConfig
from hilsim.core.keys import Keys
from hilsim.core.ros2 import types as ros2types
from hilsim.core.scenario import load_scenario

REPO = Path(__file__).resolve().parent.parent
HILSIM = [sys.executable, "-m", "hilsim.cli"]

DIST, VERSION, MODULE = "hilsim-plugin-demo", "0.1.0", "hilsim_plugin_demo"
SENSOR, SERVICE, TOPIC = "demo-imu", "imu-counter", "imu-counter/last"
FRAME = "plugin_imu"
IMU_RATE_HZ, DURATION_S = 100, 1

PLUGIN_SOURCE = '''\
"""A hilsim plug-in made by tests/test_plugins.py: a sensor kind, a service and its topic."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from hilsim.core import msgs
from hilsim.sim.sensing import Sensor, SensorParams
from hilsim.core.service import Service


class DemoImuParams(SensorParams):
    frame_id: str = Field(min_length=1, description="frame id written into every sample")


class DemoImu(Sensor):
    """An IMU that reports the truth as it is, in a frame of its own: ``imu`` from ``truth/imu``."""

    type_name = "demo-imu"
    truth_topic = "imu"
    output_topic = "imu"
    truth_type = msgs.Imu
    Params = DemoImuParams

    def measure(self, truth: msgs.Imu, stamp_ns: int) -> msgs.Imu:
        return msgs.Imu(
            header=msgs.header(stamp_ns, self.p.frame_id),
            orientation=truth.orientation,
            orientation_covariance=list(truth.orientation_covariance),
            angular_velocity=truth.angular_velocity,
            angular_velocity_covariance=list(truth.angular_velocity_covariance),
            linear_acceleration=truth.linear_acceleration,
            linear_acceleration_covariance=list(truth.linear_acceleration_covariance),
        )


class ImuCounterConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    frame_id: str = Field(min_length=1, description="count the imu samples of this frame")


class ImuCounter(Service):
    """Counts the ``imu`` samples of one frame.

    Reads: ``<prefix>/<robot>/imu`` (sensor_msgs/Imu).
    Writes: ``<prefix>/<robot>/imu-counter/last`` (sensor_msgs/Imu: each sample it counted; a topic
    this package adds to the key scheme by entry point); its health (``<prefix>/<robot>/health/imu-counter``) carries
    ``frame_id`` (from its settings), ``counted`` (samples of that frame) and ``other_frames``.
    Settings (scenario section ``imu-counter:``): ``frame_id``.
    """

    name = "imu-counter"
    Config = ImuCounterConfig
    cfg: ImuCounterConfig

    def __init__(self, scenario: Any) -> None:
        super().__init__(scenario)
        self.counted = 0
        self.other_frames = 0

    def setup(self) -> None:
        self.pub = self.publisher(self.keys.topic("imu-counter/last"))
        self.subscribe(self.keys.topic("imu"), msgs.Imu, self.on_imu)

    def on_imu(self, m: msgs.Imu, key: str) -> None:
        self.sim_ns = max(self.sim_ns, msgs.ns_of(m.header.stamp))
        if m.header.frame_id == self.cfg.frame_id:
            self.counted += 1
            self.pub.put(m)
        else:
            self.other_frames += 1

    def health_values(self) -> dict[str, Any]:
        return {"frame_id": self.cfg.frame_id, "counted": self.counted, "other_frames": self.other_frames}
'''

ENTRY_POINTS = f"""\
[hilsim.sensors]
{SENSOR} = {MODULE}:DemoImu

[hilsim.services]
{SERVICE} = {MODULE}:ImuCounter

[hilsim.topics]
{TOPIC} = hilsim.core.msgs:Imu
"""


def _record_line(path: str, data: bytes) -> str:
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return f"{path},sha256={digest},{len(data)}"


def build_wheel(out: Path) -> Path:
    """A pure-Python wheel, made by hand (no build backend, no network)."""
    info = f"{MODULE}-{VERSION}.dist-info"
    files = {
        f"{MODULE}/__init__.py": PLUGIN_SOURCE.encode(),
        f"{info}/METADATA": f"Metadata-Version: 2.1\nName: {DIST}\nVersion: {VERSION}\n".encode(),
        f"{info}/WHEEL": b"Wheel-Version: 1.0\nGenerator: tests/test_plugins.py\nRoot-Is-Purelib: true\n"
        b"Tag: py3-none-any\n",
        f"{info}/entry_points.txt": ENTRY_POINTS.encode(),
    }
    record = "\n".join([*(_record_line(p, d) for p, d in files.items()), f"{info}/RECORD,,", ""])
    wheel = out / f"{MODULE}-{VERSION}-py3-none-any.whl"
    with zipfile.ZipFile(wheel, "w", zipfile.ZIP_DEFLATED) as z:
        for p, d in files.items():
            z.writestr(p, d)
        z.writestr(f"{info}/RECORD", record)
    return wheel


@pytest.fixture(scope="module")
def plugin_site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The plug-in, installed by pip into a directory of its own (not the venv)."""
    root = tmp_path_factory.mktemp("plugin")
    wheel = build_wheel(root)
    site = root / "site"
    r = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "--no-cache-dir",
         "--disable-pip-version-check", "--target", str(site), str(wheel)],
        capture_output=True, text=True, timeout=120,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert (site / MODULE / "__init__.py").exists() and (site / f"{MODULE}-{VERSION}.dist-info").is_dir()
    return site


@pytest.fixture
def plugin_on_path(plugin_site: Path) -> Iterator[Path]:
    """``plugin_site`` on sys.path for one test; the registry's entry-point cache is cleared
    before and after, and the plug-in module forgotten, so no other test sees it."""
    registry._plugins.cache_clear()
    hilsim_keys._PLUGIN_TOPICS = None
    sys.path.insert(0, str(plugin_site))
    importlib.invalidate_caches()
    try:
        yield plugin_site
    finally:
        sys.path.remove(str(plugin_site))
        sys.modules.pop(MODULE, None)
        importlib.invalidate_caches()
        registry._plugins.cache_clear()
        hilsim_keys._PLUGIN_TOPICS = None
    assert SERVICE not in registry.names("services"), "the plug-in is still visible after the test"
    assert TOPIC not in hilsim_keys.plugin_topics(), "the plug-in's topic is still known after the test"


def write_scenario(path: Path) -> Path:
    """A scenario that extends the arm, runs the plug-in service and uses the plug-in sensor in
    place of the built-in IMU (two sensors may not write one topic)."""
    base = os.path.relpath(REPO / "config" / "arm.yaml", path.parent)
    path.write_text(textwrap.dedent(f"""\
        extends: {base}
        name: arm-plugins
        services: [physics, sensors, controller, logger, {SERVICE}]
        task:
          targets: []           # no planner, so no task
        sensors:
          imu: {{enabled: false}}
          plugin_imu: {{type: {SENSOR}, rate_hz: {IMU_RATE_HZ}, frame_id: {FRAME}}}
        {SERVICE}:
          frame_id: {FRAME}
        """))
    return path


def mentions_of_plugin() -> list[str]:
    """Files of the repository (tracked, or untracked and not ignored) that name the plug-in."""
    r = subprocess.run(["git", "grep", "-l", "--untracked", "-F", MODULE], cwd=REPO, capture_output=True, text=True)
    assert r.returncode in (0, 1), r.stderr
    return sorted(r.stdout.split())


def test_the_installed_plugin_is_found_by_entry_point(plugin_on_path: Path, tmp_path: Path) -> None:
    """In process: importlib.metadata and the registry see the plug-ins, and a scenario may name
    them (service list, sensor type, the service's own section)."""
    eps = {ep.name: ep.value for ep in importlib.metadata.entry_points(group="hilsim.sensors")}
    assert eps.get(SENSOR) == f"{MODULE}:DemoImu"
    assert importlib.metadata.version(DIST) == VERSION
    assert SENSOR in registry.names("sensors") and SERVICE in registry.names("services")
    # its topic joins the key scheme: a key for it, and its message type for the recorder
    key = Keys("hilsim", "arm").topic(TOPIC)
    assert key.startswith(f"0/arm/{TOPIC}/sensor_msgs::msg::dds_::Imu_/RIHS01_")
    assert hilsim_keys.message_type(key) is msgs.Imu
    # the built-in services first, in their table's order, then the plug-ins
    builtin = list(registry.BUILTIN["services"])
    assert registry.names("services")[: len(builtin)] == builtin and builtin[:2] == ["physics", "sensors"]

    from hilsim.core.service import Service
    from hilsim.sim.sensing import Sensor, sensor_class

    assert issubclass(sensor_class(SENSOR), Sensor)
    counter_cls = registry.service_class(SERVICE)
    assert issubclass(counter_cls, Service) and counter_cls.name == SERVICE

    sc = load_scenario(write_scenario(tmp_path / "arm-plugins.yaml"))
    assert sc.processes() == ["physics", "sensors", "controller", "logger", SERVICE]
    assert counter_cls(sc).cfg.frame_id == FRAME  # its section, validated by its Config
    from hilsim.services.sensors import SensorService

    sensors = {s.name: s for s in SensorService(sc).sensors}
    assert sensors["plugin_imu"].type_name == SENSOR and sensors["plugin_imu"].enabled
    assert not sensors["imu"].enabled


@pytest.mark.e2e
def test_plugin_sensor_and_service_run_under_hilsim_up(plugin_site: Path, router: str, tmp_path: Path) -> None:
    """``hilsim up`` starts the plug-in service as its own process, the sensor emulator runs the
    plug-in sensor, and the service counts every sample of 1 s of sim time."""
    scenario = write_scenario(tmp_path / "arm-plugins.yaml")
    out = tmp_path / "run"
    keys = Keys()
    health: dict[str, dict[str, str]] = {}

    def on_health(s: zenoh.Sample) -> None:
        for st in msgs.decode(msgs.DiagnosticArray, s.payload.to_bytes()).status:
            health[st.name] = {kv.key: kv.value for kv in st.values}  # the last one wins: the final

    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(plugin_site), env.get("PYTHONPATH", "")) if p)
    ses = transport.open_session(ZenohConfig(connect=[router]))
    sub = ses.declare_subscriber(keys.health("*"), on_health)
    try:
        p = subprocess.Popen(
            [*HILSIM, "up", str(scenario), "--duration", str(DURATION_S), "--router", router, "--out", str(out)],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path, env=env,
            start_new_session=True,
        )
        try:
            stdout, _ = p.communicate(timeout=240)
        finally:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        time.sleep(0.3)  # the last health messages are on their way
    finally:
        sub.undeclare()
        ses.close()
    assert p.returncode == 0, stdout
    assert "clock lockstep" in stdout, stdout

    # its own process, started and announced like the built-in services
    ready = next(ln for ln in stdout.splitlines() if ln.startswith("ready:"))
    pids = {part.split(" (pid ")[0].strip(): int(part.split("(pid ")[1].rstrip(")")) for part in ready[6:].split(", ")}
    assert set(pids) == {"physics", "sensors", "controller", "logger", SERVICE}, ready
    assert len(set(pids.values())) == 5 and p.pid not in pids.values(), ready
    assert (out / f"{SERVICE}.log").exists()

    # the physics steps of 1 s are t = 0, 1, …, 1000 ms (step 0 is the state before any command);
    # the sensor samples those with k % (1000 Hz / 100 Hz) == 0: k = 0, 10, …, 1000
    expected = DURATION_S * IMU_RATE_HZ + 1
    counter = health.get(SERVICE)
    assert counter is not None, f"no health from {SERVICE}; got {sorted(health)}\n{stdout}"
    assert counter["frame_id"] == FRAME, counter  # its setting came through its Config
    assert counter["state"] == "stopped" and counter["errors"] == "0" and counter["rejected"] == "0", counter
    assert (int(counter["counted"]), int(counter["other_frames"])) == (expected, 0), counter
    sensors = health["sensors"]
    assert sensors["sensor:plugin_imu"] == f"{SENSOR} {IMU_RATE_HZ} Hz, {expected} out", sensors
    assert sensors["sensor:imu"] == "disabled", sensors
    assert health["physics"]["sim_time"] == f"{DURATION_S:.3f}", health["physics"]

    counts = json.loads((out / "record_summary.json").read_text())
    assert counts[keys.topic("imu")]["received"] == expected, counts[keys.topic("imu")]
    # the plug-in's own topic, recorded (the recorder decodes it with the plug-in's type)
    # spelled here: this process has no plug-in (its topic carries sensor_msgs/Imu)
    mine = counts[f"{keys.domain}/{keys.robot}/{TOPIC}/{msgs.type_name(msgs.Imu).replace('/msg/', '::msg::dds_::')}_/"
                  f"{ros2types.type_hash('sensor_msgs/msg/Imu')}"]
    assert mine["received"] == mine["recorded"] == expected and mine["rejected"] == 0, mine

    # the plug-in lives only in the test's directory: no file of the repository names it (but this
    # one), and the venv does not have it
    assert mentions_of_plugin() == ["tests/test_plugins.py"]
    r = subprocess.run([sys.executable, "-c", f"import importlib.metadata as m; m.distribution({DIST!r})"],
                       capture_output=True, text=True, cwd=tmp_path, timeout=60)
    assert r.returncode != 0 and "PackageNotFoundError" in r.stderr, r.stderr
