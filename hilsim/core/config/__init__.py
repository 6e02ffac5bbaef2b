"""The scenario schema: what a scenario file may say, validated with pydantic.

Only the schema lives here (and :class:`ConfigError`, :func:`format_error`, the one-line error of
a bad field). Reading files, ``extends:``, overrides and the environment is
:mod:`hilsim.core.scenario`; which robots a scenario has and what its services are called,
:mod:`hilsim.core.fleet` (below this package). Checks that need the registry of services get its
names through pydantic's validation context, which the loader supplies.

One module per concern; this package's names are theirs, so ``from hilsim.core.config import X`` is all a
caller needs:

- :mod:`~hilsim.core.config.base`: the repository's folders, default services, ``SIM``, sizes in bytes, the base model
- :mod:`~hilsim.core.config.errors`: :class:`ConfigError` and :func:`format_error`
- :mod:`~hilsim.core.config.network`: ``zenoh:`` (TLS, auth), the TLS identity from the environment, ``ros2:``
- :mod:`~hilsim.core.config.clock`: ``clock:``
- :mod:`~hilsim.core.config.robot`: ``world:``, ``joints:`` (drives), ``physics:``, ``sensors:``, ``controller:``
- :mod:`~hilsim.core.config.task`: ``planner:`` (and its criterion) and ``task:``
- :mod:`~hilsim.core.config.recorder`: ``logger:`` (bag, splits, limits, live streams)
- :mod:`~hilsim.core.config.processes`: ``fleet:`` and ``restart:``
- :mod:`~hilsim.core.config.navigator`: a rover's ``navigator:``
- :mod:`~hilsim.core.config.schema`: :class:`Scenario`, the checks across sections, :func:`require_realtime`
"""

from __future__ import annotations

from hilsim.core.config.base import (
    CONFIG_DIR,
    DEFAULT_SERVICES,
    MODELS_DIR,
    REPO_ROOT,
    SIM,
    known_services,
    parse_bytes,
)
from hilsim.core.config.clock import ClockConfig
from hilsim.core.config.errors import ConfigError, format_error
from hilsim.core.config.navigator import FollowerConfig, FootprintConfig, NavigatorConfig
from hilsim.core.config.network import TLS_ENV, Ros2Config, TlsConfig, ZenohConfig, tls_from_env
from hilsim.core.config.processes import FleetConfig, RestartConfig, RestartPolicy
from hilsim.core.config.recorder import FoxgloveConfig, LiveConfig, LoggerConfig
from hilsim.core.config.robot import (
    ControllerConfig,
    DriveConfig,
    Interface,
    JointConfig,
    PhysicsConfig,
    PidGains,
    SensorConfig,
    WorldConfig,
)
from hilsim.core.config.schema import Scenario, require_realtime
from hilsim.core.config.task import DEFAULT_CRITERION, Criterion, PlannerConfig, TaskConfig

__all__ = [
    "CONFIG_DIR", "DEFAULT_CRITERION", "DEFAULT_SERVICES", "MODELS_DIR", "REPO_ROOT", "SIM", "TLS_ENV",
    "ClockConfig", "ConfigError", "ControllerConfig", "Criterion", "DriveConfig", "FleetConfig", "FollowerConfig",
    "FootprintConfig", "FoxgloveConfig", "Interface", "JointConfig", "LiveConfig", "LoggerConfig", "NavigatorConfig",
    "PhysicsConfig", "PidGains", "PlannerConfig", "RestartConfig", "RestartPolicy", "Ros2Config", "Scenario",
    "SensorConfig", "TaskConfig", "TlsConfig", "WorldConfig", "ZenohConfig", "format_error",
    "known_services", "parse_bytes", "require_realtime", "tls_from_env",
]
