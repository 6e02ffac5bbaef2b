"""Hardware lives on the wall clock: every bridge to a device refuses lockstep with the one message of
:func:`hilsim.core.config.require_realtime` (built without a network: the check is in the constructor)."""

from __future__ import annotations

from pathlib import Path

import pytest

from hilsim.bridges.drive_emulator import DriveEmulatorService
from hilsim.bridges.gps_emulator import GpsEmulatorService
from hilsim.bridges.mavlink_bridge import MavlinkBridgeService
from hilsim.core.config import ConfigError
from hilsim.core.scenario import load_scenario

CONFIG = Path(__file__).resolve().parents[1] / "config"
TAIL = ", so the scenario needs clock.mode: realtime (got 'lockstep'; pass --clock realtime)"


@pytest.mark.parametrize(("service", "scenario", "overlay", "head"), [
    (MavlinkBridgeService, "rover-outdoor.yaml", "hil/mavlink.yaml",
     "clock.mode: bridge-mavlink talks to a device on the wall clock"),
    (GpsEmulatorService, "rover-outdoor.yaml", "hil/mavlink-emulated.yaml",
     "clock.mode: gps-emulator is a device on the wall clock"),
    (DriveEmulatorService, "hil/controller-in-the-loop.yaml", None,
     "drive-emulator: mode simulation puts a CAN host on the wall clock"),
])
def test_each_device_bridge_refuses_lockstep_in_the_same_one_line(service: type, scenario: str, overlay: str | None,
                                                                   head: str) -> None:
    sc = load_scenario(str(CONFIG / scenario), {"clock.mode": "lockstep"},
                       overlays=[CONFIG / overlay] if overlay else [])
    with pytest.raises(ConfigError) as e:
        service(sc)
    assert str(e.value) == f"{sc.source}: {head}{TAIL}"
