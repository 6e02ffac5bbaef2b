"""Loading a scenario: files, ``extends:``, overlays, ``--set`` overrides, the environment, one robot's view.

A bad file never produces a traceback: :func:`load_scenario` raises :class:`~hilsim.core.config.ConfigError`
whose message is one line naming the file, the field and what was expected, e.g.
``config/arm.yaml: controller.gains.joint_2.kp: Input should be a valid number (got 'fast')``. It
names where the bad value came from: the file, an overlay (``--hil``), or the override
(``--set controler.rate_hz=5: unknown field 'controler' …``). Fields whose shape depends on the
robot (joint names, per-joint gains, task targets, the planner library's limits) are checked
against the world model's actuated joints (:func:`check_model`), so a target of the wrong
length is refused at load, not met by a service mid-run.

Relative paths inside a scenario are resolved against the directory of the file.
Environment overrides (applied after the file): ``HILSIM_PREFIX``, ``HILSIM_ZENOH_CONNECT``
(comma-separated endpoints), ``HILSIM_ZENOH_MODE``, ``HILSIM_ZENOH_AUTH`` (``zenoh.auth``), and
``zenoh.tls`` from ``HILSIM_TLS_ROOT_CA``, ``HILSIM_TLS_CERTIFICATE``, ``HILSIM_TLS_PRIVATE_KEY``.

The schema itself is :mod:`hilsim.core.config`; this module sits above it and the registry,
so it may ask the registry which services exist.
"""

from __future__ import annotations

import copy
import json
import os
from collections.abc import Sequence
from functools import cache
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from hilsim.core import fleet, registry
from hilsim.core.config import (
    CONFIG_DIR,
    SIM,
    ConfigError,
    Scenario,
    format_error,
    require_realtime,
    tls_from_env,
)


def _context() -> dict[str, Any]:
    """What the schema's validators check against: the services the registry knows."""
    return {"services": registry.names("services")}


def _resolve_paths(data: dict[str, Any], base: Path) -> None:
    for section, keys in (("world", ("model", "urdf")), ("planner", ("library",)),
                          ("world" + REPLACE, ("model", "urdf")), ("planner" + REPLACE, ("library",))):
        d = data.get(section)
        if isinstance(d, dict):
            for k in keys:
                if isinstance(d.get(k), str) and not os.path.isabs(d[k]):
                    d[k] = str((base / d[k]).resolve())


def set_dotted(data: dict[str, Any], dotted: str, value: Any) -> None:
    """Apply an override such as ``clock.mode=realtime`` to raw scenario data."""
    parts = dotted.split(".")
    d = data
    for p in parts[:-1]:
        d = d.setdefault(p, {})
        if not isinstance(d, dict):
            raise ConfigError(f"override {dotted}: {p} is not a section")
    d[parts[-1]] = value


def parse_overrides(items: Sequence[str]) -> dict[str, Any]:
    """``--set FIELD=VALUE`` arguments -> overrides for :func:`load_scenario` (values are YAML,
    so ``seed=3`` is a number and ``clock.mode=realtime`` a string)."""
    out: dict[str, Any] = {}
    for it in items:
        k, sep, v = it.partition("=")
        if not sep:
            raise ConfigError(f"--set {it}: expected FIELD=VALUE, e.g. clock.mode=realtime")
        out[k.strip()] = yaml.safe_load(v)
    return out


def scenario_path(name_or_path: str | Path) -> Path:
    """``arm`` -> ``config/arm.yaml``; a path is taken as it is."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        return p
    return CONFIG_DIR / f"{name_or_path}.yaml"


def _read(path: Path, chain: tuple[Path, ...] = ()) -> dict[str, Any]:
    """Raw data of a scenario file, its ``extends:`` base merged under it (paths resolved)."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        avail = ", ".join(sorted(p.stem for p in CONFIG_DIR.glob("*.yaml") if _is_scenario(p)))
        where = f"{chain[-1]}: extends: " if chain else ""
        raise ConfigError(f"{where}{path}: no such scenario file (available in config/: {avail})") from None
    except OSError as e:
        raise ConfigError(f"{path}: cannot read: {e.strerror}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark else "?"
        raise ConfigError(f"{path}: {where}: not valid YAML ({getattr(e, 'problem', e)})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: (top level): expected a mapping of scenario fields, got {type(data).__name__}")
    _resolve_paths(data, path.resolve().parent)
    bases = data.pop("extends", None)
    unset = data.pop(UNSET, None)
    if bases is None:
        if unset is not None:
            raise ConfigError(f"{path}: {UNSET}: only a scenario that extends another can take fields away")
        return _merge({}, data)  # REPLACE keys of a file without a base: plain keys
    if isinstance(bases, str):
        bases = [bases]
    if not isinstance(bases, list) or not bases or not all(isinstance(b, str) for b in bases):
        raise ConfigError(f"{path}: extends: expected a scenario file path, or a list of them (got {bases!r})")
    merged: dict[str, Any] = {}
    for base in bases:  # merged in order, this file last
        base_path = (path.resolve().parent / base).resolve()
        if base_path in chain or base_path == path.resolve():
            raise ConfigError(f"{path}: extends: {base} extends itself (through {', '.join(map(str, chain))})")
        merged = _merge(merged, _read(base_path, (*chain, path.resolve())))
    _unset(merged, unset, path)
    return _merge(merged, data)


def _unset(data: dict[str, Any], fields: Any, path: Path) -> None:
    """``unset: [controller.gains, task.targets]``: these fields of the scenarios extended are taken away
    (the schema's defaults then apply, unless this file gives them anew)."""
    if fields is None:
        return
    if not isinstance(fields, list) or not all(isinstance(f, str) and f for f in fields):
        raise ConfigError(f"{path}: {UNSET}: expected a list of fields, e.g. [controller.gains, task.targets] "
                          f"(got {fields!r})")
    for f in fields:
        d: Any = data
        parts = f.split(".")
        for p in parts[:-1]:
            d = d.get(p) if isinstance(d, dict) else None
        if not isinstance(d, dict) or parts[-1] not in d:
            raise ConfigError(f"{path}: {UNSET}: {f}: no such field in the scenarios it extends")
        del d[parts[-1]]


APPEND = "+"  # ``services+: [bridge-ros2-dds]``: add to the list below instead of replacing it
REPLACE = "!"  # ``gains!: {…}``: this section replaces the one below whole instead of merging into it
UNSET = "unset"  # ``unset: [controller.gains]``: fields of the scenarios extended, taken away


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """``over`` on top of ``base``: sections merge key by key, anything else is replaced; a key
    ``name+`` adds the items of its list that ``name``'s list does not have yet (an overlay adds a
    service to whatever services the scenario has, without restating them); a key ``name!`` replaces
    ``name`` whole, a section included (a lab's arm does not inherit the Niryo's gains)."""
    out = dict(base)
    for k, v in over.items():
        if k.endswith(REPLACE):
            out[k[:-len(REPLACE)]] = _merge({}, v) if isinstance(v, dict) else v
            continue
        if k.endswith(APPEND) and isinstance(v, list):
            name = k[:-len(APPEND)]
            if isinstance(out.get(name), list):
                out[name] = [*out[name], *(x for x in v if x not in out[name])]
            else:  # nothing below says it yet: added to the schema's default when the scenario is built
                out[k] = [*out.get(k, []), *(x for x in v if x not in out.get(k, []))]
            continue
        if isinstance(v, dict):
            out[k] = _merge(out[k] if isinstance(out.get(k), dict) else {}, v)
        else:
            out[k] = v
    return out


def _apply_appends(data: dict[str, Any]) -> None:
    """``name+`` left at the top level (no file below gave ``name``): added to the field's default."""
    for k in [k for k in data if k.endswith(APPEND)]:
        name, items = k[:-len(APPEND)], data.pop(k)
        field = Scenario.model_fields.get(name)
        if field is None or not isinstance(items, list):
            data[k] = items  # the schema names the unknown field or the wrong type
            continue
        have = list(data[name]) if isinstance(data.get(name), list) else list(field.get_default(
            call_default_factory=True) or [])
        data[name] = [*have, *(x for x in items if x not in have)]


def _shown(value: Any) -> str:
    """An override's value as the user would type it after ``--set FIELD=``."""
    return json.dumps(value) if isinstance(value, list | dict) else str(value)


Layer = tuple[str, Any]  # (origin, an overlay's data or an override (field, value))


def _compose(base: dict[str, Any], layers: Sequence[Layer]) -> dict[str, Any]:
    """A fresh copy of ``base`` with ``layers`` (overlays merged, overrides set) applied in order."""
    data = copy.deepcopy(base)
    for origin, layer in layers:
        if isinstance(layer, dict):
            data = _merge(data, copy.deepcopy(layer))
            continue
        try:
            set_dotted(data, layer[0], copy.deepcopy(layer[1]))
        except ConfigError as e:
            raise ConfigError(f"{origin}: {str(e).split(': ', 1)[-1]}") from None
    return data


def load_scenario(
    name_or_path: str | Path, overrides: dict[str, Any] | None = None, overlays: Sequence[str | Path] = (),
    origins: dict[str, str] | None = None,
) -> Scenario:
    """Load, merge, override, validate, check against the robot model. A scenario file may start
    from another with ``extends: <path relative to this file>`` and change only some fields;
    ``overlays`` (e.g. a HIL file given to ``hilsim up --hil``) are merged on top in order, then
    ``overrides``.

    An error names where the bad value came from: the file, an overlay, or an override, as
    ``--set FIELD=VALUE`` or as ``origins`` names it (override key -> how it was given, e.g.
    ``{"duration": "--duration -1"}``), e.g. ``--set controler.rate_hz=5: unknown field 'controler' …``."""
    path = scenario_path(name_or_path)
    base = _read(path)
    layers: list[Layer] = []
    for o in overlays:
        op = Path(o)
        if not op.exists():
            raise ConfigError(f"{op}: no such overlay file")
        layers.append((str(op), _read(op)))
    for k, v in (overrides or {}).items():
        layers.append(((origins or {}).get(k) or f"--set {k}={_shown(v)}", (k, v)))
    try:
        return _build(path, _compose(base, layers), str(path))
    except ConfigError as e:
        if not layers:
            raise
        full = str(e)
    what = full.removeprefix(f"{path}: ")
    # the first layer with which this error appears is its origin (the last one, at the latest)
    for i in range(len(layers) + 1):
        where = layers[i - 1][0] if i else str(path)
        try:
            _build(path, _compose(base, layers[:i]), where)
        except ConfigError as e:
            if str(e) == full or str(e).removeprefix(f"{where}: ") == what:
                raise ConfigError(str(e)) from None
    raise ConfigError(full)  # not reached: the last layer reproduces the error


def _build(path: Path, data: dict[str, Any], where: str) -> Scenario:
    """The scenario from merged raw ``data`` of the file ``path``: validated, checked, or a
    one-line ConfigError starting with ``where``."""
    _apply_appends(data)
    _apply_env(data)
    _resolve_paths(data, path.resolve().parent)
    try:
        sc = Scenario.model_validate(data, context=_context())
    except ValidationError as e:
        raise ConfigError(format_error(where, e)) from None
    robots = {}
    for robot in sc.robot_overrides:  # a bad value is said when the file is read, not when that robot starts
        try:
            robots[robot] = robot_scenario(sc, robot)
        except ConfigError as e:
            raise ConfigError(f"{where}: {str(e).split(': ', 1)[-1]}") from None
    if not sc.world.model.exists():
        raise ConfigError(f"{where}: world.model: file {sc.world.model} does not exist")
    if sc.world.urdf is not None and not sc.world.urdf.exists():
        raise ConfigError(f"{where}: world.urdf: file {sc.world.urdf} does not exist")
    check_joint_servers(sc, where)
    check_model(sc, where)
    for robot, rsc in robots.items():  # what a robot's overrides change, against the same model
        check_model(rsc, where, f"robot_overrides.{robot}.")
    sc.source = path
    return sc


@cache
def _actuated_joints(model: Path, mtime_ns: int) -> tuple[str, ...]:
    import mujoco

    try:
        spec = mujoco.MjSpec.from_file(str(model))
    except Exception as e:
        raise ConfigError(f"world.model: cannot load {model}: {' '.join(str(e).split())}") from None
    return tuple(a.target for a in spec.actuators if a.trntype == mujoco.mjtTrn.mjTRN_JOINT)


def model_joints(sc: Scenario) -> list[str]:
    """The robot's joints as its services know them: the world model's actuated joints, in
    actuator order (one robot's, with ``robots`` > 1: every copy has the same)."""
    return list(_actuated_joints(sc.world.model, sc.world.model.stat().st_mtime_ns))


def check_model(sc: Scenario, where: str, field: str = "") -> None:
    """Every field whose shape depends on the robot, against its world model (one-line
    ConfigError starting with ``where``; ``field``: the prefix of the fields' names, e.g. a
    robot's ``robot_overrides.arm1.``): joint names in ``joints`` and ``controller.gains``, a
    gain for every joint, one value per joint in each of ``task.targets`` (the planner's; the
    navigator's are ``[x, y]`` or ``[x, y, yaw]``), and the planner library's per-joint ``limits``."""
    try:
        names = model_joints(sc)
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None
    model = sc.world.model
    listed = f"({', '.join(names)})"
    for j in sc.joints:
        if j != "default" and j not in names:
            raise ConfigError(f"{where}: {field}joints.{j}: no actuated joint of that name in {model} "
                              f"(joints: {', '.join(names)})")
    gains = sc.controller.gains
    groups: dict[str, list[str]] = {}  # a plug-in control law may take gains per group: *_steering
    if sc.controller.type != "joint_trajectory":
        for n in names:
            head, _, group = n.rpartition("_")
            if head and group and not group.isdigit():
                groups.setdefault(group, []).append(n)
        groups = {g: m for g, m in groups.items() if len(m) > 1}
    for k in gains:
        if k != "default" and k not in names and k not in groups:  # as the controller words it
            extra = f", groups: {', '.join(groups)}" if groups else ""
            raise ConfigError(f"{where}: {field}controller.gains.{k}: not a joint of the model (joints of "
                              f"{model.name}: {', '.join(names)}{extra}; or 'default')")
    if gains and "default" not in gains:
        bare = [n for n in names if n not in gains and not any(n in groups.get(g, ()) for g in gains)]
        if bare:  # as the controller words it
            raise ConfigError(f"{where}: {field}controller.gains: no gains for {bare[0]} and no 'default' entry "
                              f"(joints of {model.name}: {', '.join(names)})")
    if sc.world.home is not None and len(sc.world.home) != len(names):
        raise ConfigError(f"{where}: {field}world.home: expected {len(names)} values, one per joint of "
                          f"{model.name} {listed}, got {len(sc.world.home)}")
    if "planner" in sc.services:
        for i, t in enumerate(sc.task.targets):
            if len(t) != len(names):
                raise ConfigError(f"{where}: {field}task.targets[{i}]: expected {len(names)} values, one per "
                                  f"joint of {model.name} {listed}, got {len(t)}")
        _check_library_limits(sc, len(names), f"{model.name} {listed}", f"{where}: {field}")
    elif "navigator" in sc.services:
        for i, t in enumerate(sc.task.targets):
            if len(t) not in (2, 3):
                raise ConfigError(f"{where}: {field}task.targets[{i}]: a rover target is [x, y] or [x, y, yaw] "
                                  f"(got {len(t)} numbers)")


def _check_library_limits(sc: Scenario, n: int, joints: str, where: str = "") -> None:
    """The planner library's ``limits``: a number, or one per joint (a ConfigError naming the library)."""
    lib = sc.planner.library or CONFIG_DIR / "planners.yaml"
    try:
        data = yaml.safe_load(Path(lib).read_text()) or {}
        limits = data.get("limits") or {}
    except (OSError, yaml.YAMLError, AttributeError):
        return  # an unreadable library is the planner's to report, with its reason
    # the planner by name: in the library or a plug-in (said here, before anything starts, not by a dying planner)
    from importlib.metadata import entry_points

    names = set(data.get("planners") or {}) | {ep.name for ep in entry_points(group="hilsim.planners")}
    if names and sc.planner.planner not in names:
        raise ConfigError(f"{where}planner.planner: unknown planner {sc.planner.planner!r} (not in {lib} nor a "
                          f"plug-in); available: {', '.join(sorted(names))}")
    for key, v in limits.items() if isinstance(limits, dict) else ():
        if isinstance(v, list) and len(v) != n:
            raise ConfigError(f"{lib}: limits.{key}: expected a number or {n} values, one per joint of "
                              f"{joints}, got {len(v)}")


def check_joint_servers(sc: Scenario, path: Path | str) -> None:
    """External joint servers exist and the clock suits them (one-line :class:`ConfigError`)."""
    from hilsim.core import registry

    known = registry.names("services")
    for jname, j in sc.joints.items():
        if j.server == SIM:
            continue
        if j.server not in known:
            raise ConfigError(f"{path}: joints.{jname}.server: unknown server {j.server!r}; "
                              f"expected 'sim' or one of {', '.join(known)}")
        require_realtime(sc, f"joints.{jname}.server", f"{j.server!r} is an external server, which runs on the "
                         "wall clock", path)


def _is_scenario(p: Path, depth: int = 0) -> bool:
    """Whether a config file is a scenario: it names a world, or extends one that does (arm-lean.yaml)."""
    try:
        d = yaml.safe_load(p.read_text())
    except (OSError, yaml.YAMLError):
        return False
    if not isinstance(d, dict):
        return False
    if "world" in d:
        return True
    bases = d.get("extends")
    bases = [bases] if isinstance(bases, str) else bases if isinstance(bases, list) else []
    return depth < 8 and any(isinstance(b, str) and _is_scenario(p.parent / b, depth + 1) for b in bases)


def _apply_env(data: dict[str, Any]) -> None:
    if v := os.environ.get("HILSIM_PREFIX"):
        data["prefix"] = v
    z = data.setdefault("zenoh", {}) if isinstance(data.get("zenoh", {}), dict) else None
    if z is None:
        return
    if v := os.environ.get("HILSIM_ZENOH_CONNECT"):
        z["connect"] = [e.strip() for e in v.split(",") if e.strip()]
    if v := os.environ.get("HILSIM_ZENOH_MODE"):
        z["mode"] = v
    if v := os.environ.get("HILSIM_ZENOH_AUTH"):  # a Zenoh config file with user and password
        z["auth"] = v
    if tls := tls_from_env():
        z["tls"] = tls



def write_scenario(sc: Scenario, path: Path) -> None:
    path.write_text(yaml.safe_dump(sc.dump(), sort_keys=False))


def robot_scenario(sc: Scenario, robot: str) -> Scenario:
    """The scenario as one robot of the fleet sees it: ``robot`` is its name, a single robot,
    seed ``seed + k`` for robot k (its sensors' noise is its own), its ``robot_overrides`` applied."""
    from hilsim.core.config import ConfigError, Scenario, format_error
    from hilsim.core.scenario import _merge, set_dotted

    names = fleet.robot_names(sc)
    if robot not in names:
        raise ConfigError(f"{sc.source or 'scenario'}: robots: no robot {robot!r} (robots: {', '.join(names)})")
    if sc.robots == 1:
        return sc
    own = {"robot": robot, "robots": 1, "seed": sc.seed + names.index(robot), "robot_overrides": {},
           "fleet_member": True}
    over = sc.robot_overrides.get(robot)
    if not over:
        return sc.model_copy(update=own, deep=True)  # nothing shared: a robot may change its own (live gains)
    layer: dict[str, object] = {}
    for field, value in over.items():  # dotted (task.targets) or nested (task: {targets: …}) alike
        set_dotted(layer, field, value)
    data = _merge(sc.dump(), layer)
    data.update(own)
    try:
        out = Scenario.model_validate(data, context=_context())
    except ValidationError as e:
        raise ConfigError(format_error(sc.source or "scenario", e, prefix=f"robot_overrides.{robot}")) from None
    out.source, out.fleet_member = sc.source, True  # neither is in the dump
    return out


def fleet_arrays(sc: Scenario) -> bool:
    """Whether the fleet's sensors, controllers and planners run as arrays (:mod:`hilsim.core.fleet`):
    ``fleet.arrays``, robots > 1, and robots the arrays can take together (:func:`array_misfit`). Every
    process decides it alike from the scenario alone, so the fleet keys have writers wherever they have
    readers."""
    return sc.robots > 1 and sc.fleet.arrays and array_misfit(sc) is None


def array_misfit(sc: Scenario) -> str | None:
    """Why the robots of a fleet cannot be stepped as arrays, or None: each needs exactly one enabled
    encoder sensor, and all the same encoder rate and control rate (``robot_overrides`` may differ)."""
    shapes = set()
    for r in fleet.robot_names(sc):
        rsc = robot_scenario(sc, r)
        enc = [c.rate_hz for c in rsc.sensors.values() if c.type == "encoder" and c.enabled]
        if len(enc) != 1:
            return f"{r} has {len(enc)} enabled encoder sensors (arrays need exactly one)"
        shapes.add((enc[0], rsc.controller.rate_hz))
    return None if len(shapes) == 1 else "the robots' encoder or control rates differ"
