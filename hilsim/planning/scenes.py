"""Planning scenes: the scenes file, random scenes on the arm's table, and seeded planning queries.

A scenes file (``config/scenes/scenes.yaml`` is one) maps scene names to a MuJoCo world with the arm
(``model``, relative to the file) and its queries, each a start and a goal joint vector:

    scenes:
      free:
        model: free.xml
        queries:
          - {start: [0, 0, 0, 0, 0, 0], goal: [0.866, -0.789, -0.399, 0, -0.382, 0]}

:func:`generate_scenes` writes random scenes of four kinds next to such a file, seeded: ``free`` (the
table only), ``boxes`` (one to four boxes of random size and place on the table), ``window`` (a wall of
two posts and a bar across the arm's reach, leaving a narrow window, with a low block behind it: the
shipped ``narrow.xml`` at a random place and size) and ``shelf`` (a board on two legs over the table);
:func:`sample_queries` draws collision-free starts and goals in a scene. The same seed gives the same
files, byte for byte.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from hilsim.core.config import CONFIG_DIR, REPO_ROOT, ConfigError
from hilsim.planning.collision import ArmModel

SCENES = CONFIG_DIR / "scenes" / "scenes.yaml"
ARM_XML = REPO_ROOT / "models" / "arm" / "arm.xml"
KINDS = ("free", "boxes", "window", "shelf")
KIND_WEIGHTS = (0.15, 0.45, 0.25, 0.15)
BLOCKED_TRIES = 300  # draws for a query whose straight line collides before one that does not is taken
TABLE = '<geom name="table" type="box" pos="0.15 0 -0.375" size="0.45 0.6 0.375"/>'


@dataclass
class Scene:
    name: str
    model: Path  # absolute
    queries: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    kind: str = ""  # free | boxes | window | shelf for generated scenes, "" for hand-made ones


def load_scenes(path: str | Path = SCENES) -> dict[str, Scene]:
    """The scenes of a scenes file, in file order (one-line ConfigError naming the file and field)."""
    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise ConfigError(f"{p}: cannot read scenes: {e}") from None
    scenes = data.get("scenes") if isinstance(data, dict) else None
    if not isinstance(scenes, dict) or not scenes:
        raise ConfigError(f"{p}: expected 'scenes: {{name: {{model, queries}}}}'")
    out = {}
    for name, s in scenes.items():
        try:
            model = (p.parent / s["model"]).resolve()
            queries = []
            for i, q in enumerate(s.get("queries") or []):
                a, b = np.array(q["start"], float), np.array(q["goal"], float)
                if a.shape != b.shape or a.ndim != 1 or not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
                    raise ValueError(f"queries[{i}]: start and goal must be equally long lists of numbers")
                queries.append((a, b))
        except (KeyError, TypeError, ValueError) as e:
            raise ConfigError(f"{p}: scenes.{name}: expected model and queries with start/goal ({e})") from None
        out[str(name)] = Scene(str(name), model, queries, str(s.get("kind", "")))
    return out


def write_scenes(path: Path, scenes: dict[str, Scene], header: str = "") -> None:
    """A scenes file (models relative to it), numbers rounded to 1e-6 rad so that it reads back exactly."""
    doc: dict[str, Any] = {}
    for name, s in scenes.items():
        entry: dict[str, Any] = {"model": _relative(s.model, path.parent)}
        if s.kind:
            entry["kind"] = s.kind
        entry["queries"] = [{"start": [round(float(x), 6) for x in a], "goal": [round(float(x), 6) for x in b]}
                            for a, b in s.queries]
        doc[name] = entry
    text = yaml.safe_dump({"scenes": doc}, sort_keys=False, default_flow_style=None, width=200)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(f"# {line}\n" for line in header.splitlines()) + text)


def _relative(p: Path, base: Path) -> str:
    import os

    return os.path.relpath(p.resolve(), base.resolve())


# ---------------------------------------------------------------------------------- random scenes
# An obstacle box: name, centre x y z, half sizes, yaw about z. The built-in arm's scenes are written as MJCF
# text including its arm.xml; another arm's are its world with the boxes added (MjSpec), scaled to its reach.
Box = tuple[str, float, float, float, float, float, float, float]


def _box(name: str, x: float, y: float, z: float, sx: float, sy: float, sz: float, yaw: float = 0.0) -> Box:
    return (name, x, y, z, sx, sy, sz, yaw)


def _box_xml(b: Box) -> str:
    name, x, y, z, sx, sy, sz, yaw = b
    return (f'<geom name="{name}" type="box" pos="{x:.4f} {y:.4f} {z:.4f}" size="{sx:.4f} {sy:.4f} {sz:.4f}" '
            f'euler="0 0 {yaw:.4f}" rgba="0.8 0.3 0.2 1"/>')


def _on_table(rng: np.random.Generator, r_lo: float = 0.16, r_hi: float = 0.36) -> tuple[float, float, float]:
    """A place on the table within the arm's reach (r from its base) and a bearing."""
    r, th = rng.uniform(r_lo, r_hi), rng.uniform(-math.pi * 0.75, math.pi * 0.75)
    return r * math.cos(th), r * math.sin(th), th


def scene_boxes(kind: str, rng: np.random.Generator, scale: float = 1.0) -> list[Box]:
    """The obstacle boxes of a random scene of ``kind`` around an arm at the origin on a table top at z = 0
    (the table itself is always there); every length times ``scale`` (1: the built-in arm's reach)."""
    k_ = scale
    if kind == "free":
        return []
    if kind == "boxes":
        out = []
        for k in range(int(rng.integers(1, 5))):
            x, y, th = _on_table(rng, 0.16 * k_, 0.36 * k_)
            sx, sy, sz = (rng.uniform(0.015, 0.06) * k_, rng.uniform(0.015, 0.06) * k_, rng.uniform(0.04, 0.2) * k_)
            out.append(_box(f"obstacle_{k}", x, y, sz, sx, sy, sz, th))
        return out
    if kind == "window":
        # a wall across the bearing th at distance r: two posts and a bar leave a window of width w,
        # height h above a low block; the arm reaches through the window or around the posts
        x, y, th = _on_table(rng, 0.2 * k_, 0.3 * k_)
        w, h = rng.uniform(0.16, 0.3) * k_, rng.uniform(0.25, 0.42) * k_
        tx, ty = -math.sin(th), math.cos(th)  # along the wall
        half = w / 2 + 0.03 * k_
        post_h = h / 2 + 0.02 * k_
        t = 0.03 * k_
        return [
            _box("post_a", x + half * tx, y + half * ty, post_h, t, t, post_h, th),
            _box("post_b", x - half * tx, y - half * ty, post_h, t, t, post_h, th),
            _box("bar", x, y, h + 0.02 * k_, t, half + t, 0.02 * k_, th),
            _box("block", x, y, rng.uniform(0.05, 0.13) * k_, t, t, rng.uniform(0.05, 0.13) * k_, th),
        ]
    if kind == "shelf":
        x, y, th = _on_table(rng, 0.2 * k_, 0.32 * k_)
        z, half = rng.uniform(0.12, 0.3) * k_, rng.uniform(0.08, 0.18) * k_
        tx, ty = -math.sin(th), math.cos(th)
        leg = 0.015 * k_
        return [
            _box("board", x, y, z, rng.uniform(0.05, 0.1) * k_, half, 0.01 * k_, th),
            _box("leg_a", x + half * tx, y + half * ty, z / 2, leg, leg, z / 2, th),
            _box("leg_b", x - half * tx, y - half * ty, z / 2, leg, leg, z / 2, th),
        ]
    raise ValueError(f"unknown scene kind {kind!r}; expected one of {KINDS}")


def scene_geoms(kind: str, rng: np.random.Generator) -> list[str]:
    """The built-in arm's obstacle geoms (MJCF text) of a random scene of ``kind``."""
    return [_box_xml(b) for b in scene_boxes(kind, rng)]


def scene_xml(name: str, kind: str, geoms: list[str], arm_xml: str) -> str:
    body = "\n    ".join([TABLE, *geoms])
    return (f'<!-- generated by hilsim plan learn / hilsim plan scenes: scene "{name}", kind {kind} -->\n'
            f'<mujoco model="hilsim_scene_{name}">\n  <include file="{arm_xml}"/>\n  <worldbody>\n'
            f"    {body}\n  </worldbody>\n</mujoco>\n")


def sample_queries(arm: ArmModel, n: int, rng: np.random.Generator, blocked: float = 0.5,
                   max_tries: int = 20000) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` queries: starts and goals drawn uniformly within the joint limits (one turn about the home
    pose for joints that turn more: :meth:`ArmModel.sampling_bounds`), valid (no contact
    closer than the clearance), rounded to 1e-6 rad (as a scenes file keeps them), at least 0.5 rad
    apart (max-norm) so that there is something to plan. A fraction ``blocked`` of them (every
    second one at 0.5) must have a straight joint line that collides: drawn uniformly, most
    queries could go straight, which is not where planners differ."""
    lo, hi = arm.sampling_bounds()

    def valid_q() -> np.ndarray:
        for _ in range(max_tries):
            q = np.round(rng.uniform(lo, hi), 6)
            if arm.is_valid(q):
                return q
        raise ConfigError(f"{arm.path}: no valid configuration in {max_tries} random draws")

    out: list[tuple[np.ndarray, np.ndarray]] = []
    tries = 0
    while len(out) < n:
        a, b = valid_q(), valid_q()
        if np.max(np.abs(a - b)) < 0.5:
            continue
        tries += 1
        k = len(out)
        want_blocked = math.floor((k + 1) * blocked) > math.floor(k * blocked)
        if want_blocked and tries < BLOCKED_TRIES and arm.motion_valid(a, b, 0.01):
            continue  # a free straight line where a blocked one is due (a scene without one: take it)
        out.append((a, b))
        tries = 0
    return out


def generate_scenes(out_dir: Path, count: int, seed: int, queries: int, clearance: float = 0.005,
                    prefix: str = "gen", world: Path | None = None) -> dict[str, Scene]:
    """``count`` random scenes (kinds drawn with KIND_WEIGHTS), their MJCF files written into
    ``out_dir``, each with ``queries`` sampled queries; everything from ``seed``. ``world``: another arm's
    world (a scenario's ``world.model``), the obstacles placed and sized for its reach
    (:func:`world_scene_xml`); without it, the built-in arm on its table."""
    rng = np.random.default_rng(seed)
    out_dir.mkdir(parents=True, exist_ok=True)
    frame = arm_frame(world, clearance) if world is not None else None
    scenes = {}
    for i in range(count):
        kind = str(rng.choice(KINDS, p=KIND_WEIGHTS))
        name = f"{prefix}{seed}_{i:03d}_{kind}"
        path = out_dir / f"{name}.xml"
        if world is None or frame is None:
            path.write_text(scene_xml(name, kind, scene_geoms(kind, rng), _relative(ARM_XML, out_dir)))
        else:
            path.write_text(world_scene_xml(world, name, kind, scene_boxes(kind, rng, frame[1]), frame[0], out_dir))
        arm = ArmModel(path, clearance)
        scenes[name] = Scene(name, path.resolve(), sample_queries(arm, queries, rng), kind)
    return scenes


BUILTIN_REACH = 0.651  # m: the built-in arm's reach as arm_frame measures it (scale 1 of scene_boxes)
REACH_SAMPLES = 256


def arm_frame(world: Path, clearance: float = 0.005) -> tuple[np.ndarray, float]:
    """(where the arm's base stands, its reach as a multiple of the built-in arm's) in a world: the base is
    the arm's root body at the home pose, the reach the farthest the ``tool`` site gets from it over
    random poses (a fixed seed)."""
    import mujoco

    arm = ArmModel(world, clearance)
    m = arm.model
    b = int(m.jnt_bodyid[arm.joint_ids[0]])
    while int(m.body_parentid[b]) != 0:
        b = int(m.body_parentid[b])
    arm.set_q(arm.home())
    base = arm.data.xpos[b].copy()
    site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "tool")
    if site < 0:
        raise ConfigError(f"{world}: no site named 'tool' (where the arm's tool is: its reach sizes the scenes)")
    lo, hi = arm.sampling_bounds()
    rng = np.random.default_rng(12345)
    reach = 0.0
    for q in rng.uniform(lo, hi, size=(REACH_SAMPLES, arm.n)):
        arm.set_q(q)
        reach = max(reach, float(np.linalg.norm(arm.data.site_xpos[site] - base)))
    return base, reach / BUILTIN_REACH


def world_scene_xml(world: Path, name: str, kind: str, boxes: list[Box], base: np.ndarray, out_dir: Path) -> str:
    """Another arm's world with the obstacle boxes standing around its base (MuJoCo's spec API), as MJCF
    text for ``out_dir`` (its mesh and texture folders made relative to there)."""
    import os

    import mujoco

    spec = mujoco.MjSpec.from_file(str(world))
    spec.modelname = f"hilsim_scene_{name}"
    for bname, x, y, z, sx, sy, sz, yaw in boxes:
        g = spec.worldbody.add_geom()
        g.name, g.type = bname, mujoco.mjtGeom.mjGEOM_BOX
        g.pos = [base[0] + x, base[1] + y, base[2] + z]
        g.size = [sx, sy, sz]
        g.quat = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
        g.rgba = [0.8, 0.3, 0.2, 1.0]
    folders = {}
    for attr in ("meshdir", "texturedir"):  # absolute for MuJoCo now, relative to out_dir in the text
        d = getattr(spec, attr)
        where = Path(d) if d and os.path.isabs(d) else Path(world).resolve().parent / (d or "")
        setattr(spec, attr, str(where))
        folders[attr] = (str(where), os.path.relpath(where, out_dir.resolve()))
    xml = spec.to_xml()
    for attr, (absolute, rel) in folders.items():
        xml = xml.replace(f'{attr}="{absolute}"', f'{attr}="{rel}"')
    return f"<!-- generated by hilsim plan learn / hilsim plan scenes: scene \"{name}\", kind {kind} -->\n" + xml


def world_sha256(model: Path) -> str:
    """What a scene's world is, whatever its file's name or folder: a hash of its static geoms (type, size,
    place) and of its arm's joints, the first 16 hex digits."""
    import hashlib

    arm = ArmModel(model)
    m = arm.model
    h = hashlib.sha256(",".join(arm.joint_names).encode())
    for g in range(m.ngeom):
        if m.geom_bodyid[g] == 0:
            for v in (m.geom_type[g:g + 1], m.geom_size[g], m.geom_pos[g], m.geom_quat[g]):
                h.update(np.round(np.asarray(v, float), 6).tobytes())
    return h.hexdigest()[:16]


def query_sha256(start: np.ndarray, goal: np.ndarray) -> str:
    """A query's start and goal as a scenes file keeps them (1e-6 rad), hashed: the first 16 hex digits."""
    import hashlib

    q = np.round(np.concatenate([np.asarray(start, float), np.asarray(goal, float)]), 6) + 0.0  # no -0.0
    return hashlib.sha256(q.tobytes()).hexdigest()[:16]


def with_sampled_queries(scenes: dict[str, Scene], per_scene: int, seed: int, clearance: float = 0.005
                         ) -> dict[str, Scene]:
    """The scenes with ``per_scene`` more sampled queries each (after their own), seeded per scene."""
    out = {}
    for k, (name, s) in enumerate(scenes.items()):
        rng = np.random.default_rng([seed, k])
        extra = sample_queries(ArmModel(s.model, clearance), per_scene, rng) if per_scene else []
        out[name] = Scene(name, s.model, [*s.queries, *extra], s.kind)
    return out
