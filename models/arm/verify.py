#!/usr/bin/env python3
"""Checks for the arm model files.  Run:  python models/arm/verify.py

1. arm.xml, tabletop.xml and arm.urdf compile with MuJoCo.
2. Inertias in arm.xml equal MuJoCo's own geom-derived inertias (cross-check of generate.py).
3. URDF kinematics: an independent numpy forward kinematics parsed from arm.urdf, and MuJoCo's
   compiled URDF, both match the MJCF link frames and tool site at random configurations.
4. Gravity sanity: with no control the arm falls.
5. PD + gravity compensation (qfrc_bias through the motors) holds every target within 0.005 rad
   at dt = 1 ms, and tracks a smooth move home -> target.
6. targets.yaml: limits, collision-free, tool above table, straight-line collision check.
Exits non-zero if any check fails.
"""
from __future__ import annotations

import itertools
import math
import os
import sys
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import yaml

HERE = os.path.dirname(os.path.abspath(__file__))
P = lambda f: os.path.join(HERE, f)  # noqa: E731
FAIL = []


def check(ok, msg):
    print(("  PASS " if ok else "  FAIL ") + msg)
    if not ok:
        FAIL.append(msg)


# ---------------------------------------------------------------- 1. loading
print("1. loading")
models = {}
for f in ("arm.xml", "tabletop.xml", "arm.urdf"):
    try:
        models[f] = mujoco.MjModel.from_xml_path(P(f))
        m = models[f]
        check(True, f"{f}: nbody={m.nbody} njnt={m.njnt} nu={m.nu} ngeom={m.ngeom} "
                    f"mass={m.body_subtreemass[0]:.3f} kg")
    except Exception as e:  # pragma: no cover
        check(False, f"{f}: {e}")
if len(models) < 3:
    sys.exit(1)
arm, world, urdf = models["arm.xml"], models["tabletop.xml"], models["arm.urdf"]
JN = [f"joint_{i}" for i in range(1, 7)]
LINKS = ["base_link", "shoulder_link", "arm_link", "elbow_link", "forearm_link", "wrist_link", "hand_link"]
check([arm.joint(i).name for i in range(arm.njnt)] == JN, "joint order joint_1..joint_6")
check([arm.actuator(i).name for i in range(arm.nu)] == JN, "actuator order joint_1..joint_6")
check(all(arm.actuator(i).trnid[0] == arm.joint(JN[i]).id for i in range(6)), "actuator i drives joint i")
check(arm.opt.timestep == 0.001 and arm.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST,
      "timestep 0.001, implicitfast")
check(world.opt.timestep == 0.001 and world.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST,
      "tabletop inherits timestep 0.001, implicitfast")
for g in ("table", "obstacle", "floor"):
    check(mujoco.mj_name2id(world, mujoco.mjtObj.mjOBJ_GEOM, g) >= 0, f"tabletop geom '{g}' exists")
check(mujoco.mj_name2id(world, mujoco.mjtObj.mjOBJ_SITE, "tool") >= 0, "site 'tool' exists")
print(f"  total mass: {arm.body_subtreemass[0]:.3f} kg; per link: "
      + ", ".join(f"{n}={arm.body(n).mass[0]:.3f}" for n in LINKS))

# ------------------------------------------------ 2. inertia cross-check
print("2. inertia: explicit <inertial> (generate.py) vs MuJoCo geom-derived")
xml = open(P("arm.xml")).read()
xml_geom = xml.replace('<compiler angle="radian" autolimits="true"/>',
                       '<compiler angle="radian" autolimits="true" inertiafromgeom="true"/>')
xml_geom = "\n".join(l for l in xml_geom.splitlines() if "<inertial " not in l)
mg = mujoco.MjModel.from_xml_string(xml_geom)


def body_I(m, b):
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, m.body_iquat[b])
    R = R.reshape(3, 3)
    return m.body_ipos[b], R @ np.diag(m.body_inertia[b]) @ R.T


worst = 0.0
for n in LINKS:
    c1, I1 = body_I(arm, arm.body(n).id)
    c2, I2 = body_I(mg, mg.body(n).id)
    rel = np.abs(I1 - I2).max() / np.abs(I2).max()
    worst = max(worst, rel, np.abs(c1 - c2).max())
    if rel > 1e-5 or np.abs(c1 - c2).max() > 1e-9 or abs(arm.body(n).mass[0] - mg.body(n).mass[0]) > 1e-12:
        print(f"    mismatch {n}: rel {rel:.2e}")
check(worst < 1e-5, f"masses, COMs and inertia tensors agree (worst rel. diff {worst:.1e})")

# ------------------------------------------------ 3. URDF kinematics
print("3. URDF kinematics vs MJCF")


def rpy_R(r, p, y):
    cr, sr, cp, sp, cy, sy = map(float, (math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)))
    return (np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
            @ np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]]))


def axis_R(a, q):
    a = np.asarray(a, float) / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(q) * K + (1 - math.cos(q)) * K @ K


root = ET.parse(P("arm.urdf")).getroot()
ujoints = {}
for j in root.findall("joint"):
    o = j.find("origin")
    ujoints[j.find("child").get("link")] = dict(
        name=j.get("name"), type=j.get("type"), parent=j.find("parent").get("link"),
        xyz=np.array([float(v) for v in o.get("xyz").split()]),
        R=rpy_R(*[float(v) for v in o.get("rpy").split()]),
        axis=np.array([float(v) for v in j.find("axis").get("xyz").split()]) if j.find("axis") is not None else None,
        limit=j.find("limit"))


def urdf_fk(qmap):
    T = {"base_link": (np.zeros(3), np.eye(3))}
    pending = dict(ujoints)
    while pending:
        for child, j in list(pending.items()):
            if j["parent"] in T:
                p, R = T[j["parent"]]
                Rj = R @ j["R"]
                if j["type"] == "revolute":
                    Rj = Rj @ axis_R(j["axis"], qmap[j["name"]])
                T[child] = (p + R @ j["xyz"], Rj)
                del pending[child]
    return T


# limits / effort / velocity identical in both formats
for i, n in enumerate(JN):
    lim = ujoints[next(c for c, j in ujoints.items() if j["name"] == n)]["limit"]
    jr = arm.jnt_range[arm.joint(n).id]
    ok = (abs(float(lim.get("lower")) - jr[0]) < 1e-12 and abs(float(lim.get("upper")) - jr[1]) < 1e-12
          and abs(float(lim.get("effort")) - arm.actuator_ctrlrange[i, 1]) < 1e-12)
    check(ok, f"{n}: URDF limit [{lim.get('lower')}, {lim.get('upper')}] effort {lim.get('effort')} "
              f"velocity {lim.get('velocity')} == MJCF range/ctrlrange")

rng = np.random.default_rng(1)
da, du = mujoco.MjData(arm), mujoco.MjData(urdf)
e_np = e_mj = 0.0
for k in range(50):
    q = np.zeros(6) if k == 0 else rng.uniform(arm.jnt_range[:, 0], arm.jnt_range[:, 1])
    da.qpos[:] = q
    mujoco.mj_kinematics(arm, da)
    for i, n in enumerate(JN):
        du.qpos[urdf.jnt_qposadr[urdf.joint(n).id]] = q[i]
    mujoco.mj_kinematics(urdf, du)
    T = urdf_fk(dict(zip(JN, q, strict=False)))
    for n in LINKS:
        p_ref, R_ref = da.body(n).xpos, da.body(n).xmat.reshape(3, 3)
        e_np = max(e_np, np.abs(T[n][0] - p_ref).max(), np.abs(T[n][1] - R_ref).max())
        e_mj = max(e_mj, np.abs(du.body(n).xpos - p_ref).max(), np.abs(du.body(n).xmat.reshape(3, 3) - R_ref).max())
    e_np = max(e_np, np.abs(T["tool_link"][0] - da.site("tool").xpos).max())
    e_mj = max(e_mj, np.abs(du.body("tool_link").xpos - da.site("tool").xpos).max())
check(e_np < 1e-9, f"numpy FK of arm.urdf == MJCF link frames + tool site, 50 configs (max err {e_np:.1e})")
check(e_mj < 1e-9, f"MuJoCo-compiled arm.urdf == MJCF link frames + tool site, 50 configs (max err {e_mj:.1e})")
e_in = max(np.abs(urdf.body(n).inertia - arm.body(n).inertia).max() + np.abs(urdf.body(n).mass - arm.body(n).mass).max()
           for n in LINKS)
check(e_in < 1e-9, f"URDF masses/principal inertias == MJCF (max diff {e_in:.1e})")

# ------------------------------------------------ 4. gravity sanity
print("4. gravity, no control (arm.xml, from zero config, 1 s)")
d = mujoco.MjData(arm)
mujoco.mj_forward(arm, d)
for _ in range(1000):
    mujoco.mj_step(arm, d)
print(f"  q after 1 s: {np.round(d.qpos, 3)}")
check(np.abs(d.qpos[1:3]).max() > 0.3, "arm falls (joint_2/joint_3 move > 0.3 rad)")

# self-collision statistics (information only)
ds = mujoco.MjData(arm)
rng = np.random.default_rng(2)
nself = 0
for _ in range(2000):
    ds.qpos[:] = rng.uniform(arm.jnt_range[:, 0], arm.jnt_range[:, 1])
    mujoco.mj_forward(arm, ds)
    nself += ds.ncon > 0
print(f"  info: {nself / 20:.1f}% of 2000 uniformly random in-limit configurations have self-contact "
      f"(non-adjacent links; adjacent pairs are excluded)")

# ------------------------------------------------ 6 (first, 5 needs targets). targets
cfg = yaml.safe_load(open(P("targets.yaml")))
check(cfg["joint_names"] == JN, "targets.yaml joint_names")
home = np.array(cfg["home"], float)
targets = [np.array(t, float) for t in cfg["targets"]]
names = cfg["target_names"]
ARM_BODIES = set(range(world.body("shoulder_link").id, world.nbody)) | {world.body("base_link").id}
dw = mujoco.MjData(world)


def arm_contacts(q):
    dw.qpos[:] = q
    mujoco.mj_forward(world, dw)
    out = set()
    for i in range(dw.ncon):
        c = dw.contact[i]
        if world.geom_bodyid[c.geom1] in ARM_BODIES or world.geom_bodyid[c.geom2] in ARM_BODIES:
            out.add(tuple(sorted((world.geom(c.geom1).name, world.geom(c.geom2).name))))
    return out


def tool(q):
    dw.qpos[:] = q
    mujoco.mj_kinematics(world, dw)
    return dw.site("tool").xpos.copy()


print("6. targets (tabletop.xml)")
lo, hi = world.jnt_range[:, 0], world.jnt_range[:, 1]
for n, q in [("home", home), *list(zip(names, targets, strict=False))]:
    inlim = bool(np.all(q >= lo) and np.all(q <= hi))
    c = arm_contacts(q)
    t = tool(q)
    check(inlim and not c and t[2] > 0, f"{n:5s} q={q.tolist()} tool=({t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f}) "
                                         f"in-limits={inlim} contacts={sorted(c)}")
print("  straight joint-space lines, 100 points, contacts involving arm geoms:")
pairs = list(zip(names, targets, strict=False))
seq = list(itertools.pairwise(pairs)) + [(pairs[-1], pairs[0])] + [(("home", home), p) for p in pairs]
n_colliding_consecutive = 0
for k, ((na, qa), (nb, qb)) in enumerate(seq):
    hits, geoms = [], set()
    for s in np.linspace(0, 1, 100):
        c = arm_contacts((1 - s) * qa + s * qb)
        if c:
            hits.append(s)
            geoms |= c
    if k < len(pairs) - 1 and hits:
        n_colliding_consecutive += 1
    desc = (f"COLLIDES at {len(hits)}/100 points, s in [{min(hits):.2f}, {max(hits):.2f}], pairs {sorted(geoms)}"
            if hits else "free")
    print(f"    {na:5s} -> {nb:5s}: {desc}")
check(n_colliding_consecutive >= 1, "at least one consecutive target pair collides on the straight line")

# ------------------------------------------------ 5. PD + gravity compensation
print("5. PD + gravity compensation through the motors (tabletop.xml, dt=1 ms)")
KP = np.array([80, 80, 80, 15, 15, 10], float)
KD = np.array([3, 3, 3, 0.4, 0.4, 0.3], float)
print(f"  kp={KP.tolist()} kd={KD.tolist()}  u = clip(kp*e - kd*qdot + qfrc_bias, ctrlrange)")


def pd(m, d, qref):
    u = KP * (qref - d.qpos) - KD * d.qvel + d.qfrc_bias
    d.ctrl[:] = np.clip(u, m.actuator_ctrlrange[:, 0], m.actuator_ctrlrange[:, 1])


for n, q in [("home", home), *list(zip(names, targets, strict=False))]:
    # (a) hold: start at rest at the target, 3 s
    d = mujoco.MjData(world)
    d.qpos[:] = q
    mujoco.mj_forward(world, d)
    err = 0.0
    for _ in range(3000):
        pd(world, d, q)
        mujoco.mj_step(world, d)
        err = max(err, np.abs(d.qpos - q).max())
    check(err < 0.005, f"hold {n:5s}: max |q - q_ref| over 3 s = {err:.2e} rad")
    # (a') disturbed hold: start 0.05 rad off on every joint, must settle inside 0.005 rad
    d = mujoco.MjData(world)
    d.qpos[:] = q + 0.05 * np.array([1, -1, 1, -1, 1, -1])
    mujoco.mj_forward(world, d)
    t_in, last = None, 0.0
    for i in range(3000):
        pd(world, d, q)
        mujoco.mj_step(world, d)
        e = np.abs(d.qpos - q).max()
        if e >= 0.005:
            t_in = None
        elif t_in is None:
            t_in = (i + 1) * 0.001
        if i >= 2000:
            last = max(last, e)
    check(last < 0.005 and t_in is not None,
          f"hold {n:5s} from 0.05 rad offset: settled (<0.005 rad for good) after {t_in:.3f} s, "
          f"max err over last 1 s {last:.2e} rad")
    # information only: same hold without gravity compensation
    d = mujoco.MjData(world)
    d.qpos[:] = q
    mujoco.mj_forward(world, d)
    for _ in range(3000):
        d.ctrl[:] = np.clip(KP * (q - d.qpos) - KD * d.qvel, world.actuator_ctrlrange[:, 0],
                            world.actuator_ctrlrange[:, 1])
        mujoco.mj_step(world, d)
    print(f"  info {n:5s}: PD without gravity compensation sags by {np.abs(d.qpos - q).max():.3f} rad")
# (b) smooth move home -> target (quintic, 2 s) then hold 1 s (these straight lines are collision-free)
for n, q in zip(names, targets, strict=False):
    d = mujoco.MjData(world)
    d.qpos[:] = home
    mujoco.mj_forward(world, d)
    track, ncon, umax = 0.0, 0, np.zeros(6)
    for i in range(3000):
        s = min(i * 0.001 / 2.0, 1.0)
        qr = home + (q - home) * (10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5)
        pd(world, d, qr)
        umax = np.maximum(umax, np.abs(d.ctrl))
        mujoco.mj_step(world, d)
        track = max(track, np.abs(d.qpos - qr).max())
        ncon += d.ncon > 0
    final = np.abs(d.qpos - q).max()
    check(final < 0.005, f"move home->{n:5s} in 2 s + 1 s hold: final err {final:.2e} rad, max tracking err "
                         f"{track:.2e} rad, steps with contact {ncon}, max |u| {np.round(umax, 2).tolist()}")

print("\nRESULT:", "ALL PASS" if not FAIL else f"{len(FAIL)} FAILED: {FAIL}")
sys.exit(1 if FAIL else 0)
