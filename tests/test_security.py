"""TLS with client certificates and Zenoh access control, on loopback (docs/security.md).

The router runs the shipped config (config/security/router.json5) with certificates from
scripts/make-certs.sh; every hilsim process is a TLS client of it with an identity. Judged from
outside: who can connect, what an observer reads, and, for what it may not do, the physics truth
(the arm does not move) and physics' own counters (its attempts never reached physics)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh
from util import REPO, finish, wait_until

from hilsim.core import msgs, transport
from hilsim.core.config import TlsConfig, ZenohConfig
from hilsim.core.keys import Keys

pytestmark = pytest.mark.e2e
HILSIM = [sys.executable, "-m", "hilsim.cli"]
TARGET = [0.5, -0.4, 0.2, 0.0, -0.5, 0.0]


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A directory with router.json5 and certs/ from scripts/make-certs.sh (its paths are relative)."""
    if shutil.which("openssl") is None:
        if os.environ.get("CI") == "true":
            pytest.fail("openssl is missing: scripts/test.sh installs it")
        pytest.skip("openssl is not installed: cannot make certificates")
    d = tmp_path_factory.mktemp("security")
    shutil.copy(REPO / "config" / "security" / "router.json5", d / "router.json5")
    subprocess.run(["bash", str(REPO / "scripts" / "make-certs.sh"), str(d / "certs")], check=True,
                   capture_output=True, timeout=60)
    return d


def identity(pki: Path, who: str) -> TlsConfig:
    c = pki / "certs"
    return TlsConfig(root_ca=c / "ca.pem", certificate=c / f"{who}.pem", private_key=c / f"{who}.key")


def tls_env(pki: Path, who: str) -> dict[str, str]:
    t = identity(pki, who)
    return {**os.environ, "HILSIM_TLS_ROOT_CA": str(t.root_ca), "HILSIM_TLS_CERTIFICATE": str(t.certificate),
            "HILSIM_TLS_PRIVATE_KEY": str(t.private_key)}


@pytest.fixture
def secure_router(pki: Path) -> Iterator[str]:
    """``hilsim router --config router.json5`` on a free loopback port; its tls/ endpoint."""
    ep = f"tls/127.0.0.1:{transport.free_port()}"
    log = open(pki / "router.log", "w")
    p = subprocess.Popen([*HILSIM, "router", "--config", str(pki / "router.json5"), "--listen", ep],
                         stdout=log, stderr=subprocess.STDOUT, cwd=REPO, start_new_session=True)
    try:
        ok = wait_until(lambda: p.poll() is not None or "listening" in (pki / "router.log").read_text(), 30)
        assert ok and p.poll() is None, (pki / "router.log").read_text()
        yield ep
    finally:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
        log.close()


def _open(ep: str, tls: TlsConfig | None = None, raw: dict[str, str] | None = None) -> zenoh.Session:
    """A client session; ``raw``: TLS settings given to Zenoh directly (what hilsim would refuse)."""
    if raw is None:
        return transport.open_session(ZenohConfig(mode="client", connect=[ep], tls=tls))
    conf = transport.zenoh_config(ZenohConfig(mode="client", connect=[ep]))
    for k, v in raw.items():
        conf.insert_json5(f"transport/link/tls/{k}", f'"{v}"')
    try:
        return zenoh.open(conf)
    except zenoh.ZError as e:
        raise ConnectionError(str(e)) from e


def test_a_client_without_a_valid_certificate_cannot_connect(pki: Path, secure_router: str) -> None:
    certs = pki / "certs"
    # no client certificate at all (it trusts the router's CA, but has nothing to show)
    with pytest.raises(ConnectionError):
        _open(secure_router, raw={"root_ca_certificate": str(certs / "ca.pem")})
    # a certificate from another CA (a second throw-away set)
    other = pki / "other"
    subprocess.run(["bash", str(REPO / "scripts" / "make-certs.sh"), str(other)], check=True, capture_output=True)
    with pytest.raises(ConnectionError):
        _open(secure_router, raw={"root_ca_certificate": str(certs / "ca.pem"),
                                  "connect_certificate": str(other / "workstation.pem"),
                                  "connect_private_key": str(other / "workstation.key")})
    # plain TCP to the TLS port
    with pytest.raises(ConnectionError):
        _open(secure_router.replace("tls/", "tcp/"))
    # and the control: an identity signed by the CA gets in
    _open(secure_router, identity(pki, "observer")).close()


class Truth:
    """Physics truth and physics' health, read by an identity that may read."""

    def __init__(self, session: zenoh.Session) -> None:
        self.keys = Keys()
        self.positions: list[list[float]] = []
        self.physics: dict[str, str] = {}
        self.subs = [session.declare_subscriber(self.keys.truth("joint_states"), self._on_truth),
                     session.declare_subscriber(self.keys.health("physics"), self._on_health)]

    def _on_truth(self, s: zenoh.Sample) -> None:
        self.positions.append(list(msgs.decode(msgs.JointState, s.payload.to_bytes()).position))

    def _on_health(self, s: zenoh.Sample) -> None:
        h = msgs.decode(msgs.DiagnosticArray, s.payload.to_bytes())
        self.physics = {kv.key: kv.value for kv in h.status[0].values}

    def now(self) -> np.ndarray:
        return np.array(self.positions[-1])


def _tool(pki: Path, who: str, ep: str, *args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*HILSIM, *args, "--connect", ep], env=tls_env(pki, who), capture_output=True,
                          text=True, cwd=REPO, timeout=timeout)


def test_a_read_only_identity_reads_but_cannot_move_the_robot(pki: Path, secure_router: str,
                                                              tmp_path: Path) -> None:
    ep = secure_router
    # the services run as "workstation"; no task: the arm holds where it starts until told
    p = subprocess.Popen([*HILSIM, "up", "arm", "--router", ep, "--no-logger", "--set", "task.targets=[]",
                          "--out", str(tmp_path / "run")], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                         text=True, cwd=REPO, start_new_session=True, env=tls_env(pki, "workstation"))
    observer = _open(ep, identity(pki, "observer"))
    try:
        truth = Truth(observer)
        assert wait_until(lambda: len(truth.positions) > 200, 120), "no physics truth reached the observer"
        # reads: hilsim topic echo as the observer
        echo = _tool(pki, "observer", ep, "topic", "echo", "/arm/joint_states", "--count", "2", "--json")
        assert echo.returncode == 0 and echo.stdout.count("position") >= 2, echo.stdout + echo.stderr
        before = truth.now()
        n_before = len(truth.positions)

        # 1. joint commands, the way a service sends them: announced writer, attachment, every joint
        keys = Keys()
        token_key, gid = keys.writer_token(keys.topic("joint_commands"))
        token = observer.liveliness().declare_token(token_key)
        pub = transport.publisher(observer, keys.topic("joint_commands"))
        names = [f"joint_{i}" for i in range(1, 7)]
        for seq in range(1, 200):
            cmd = msgs.JointState(header=msgs.header(0), name=names, position=[], velocity=[],
                                  effort=[0.0, 80.0, 0.0, 0.0, 0.0, 0.0])
            pub.put(msgs.encode(cmd), attachment=transport.attachment_bytes(seq, gid))
            time.sleep(0.005)
        pub.undeclare()
        token.undeclare()
        # 2. a move goal and 3. gains that would let the arm fall
        goal = _tool(pki, "observer", ep, "goal", "arm", "--joints", *map(str, TARGET), "--timeout", "5")
        gains = _tool(pki, "observer", ep, "gains", "arm", "joint_2.kp=0", "joint_2.kd=0", "joint_2.ki=0")
        assert goal.returncode != 0 and "accepted" not in goal.stdout, goal.stdout + goal.stderr
        assert gains.returncode != 0 and gains.stdout.startswith("not set"), gains.stdout + gains.stderr
        assert wait_until(lambda: len(truth.positions) > n_before + 500, 60), "physics stopped"
        moved = np.abs(truth.now() - before).max()
        assert moved < 1e-3, f"the arm moved {moved:.4f} rad after the observer's attempts"
        # refused by the router: physics never received the observer's commands (a sample from an
        # unannounced writer that reached it would be counted as rejected there)
        assert wait_until(lambda: "msgs_in" in truth.physics, 10)
        assert truth.physics.get(f"rejected:{keys.topic('joint_commands')}", "0") == "0", truth.physics

        # the control: the same goal from the operator identity is accepted and moves the arm
        ok = _tool(pki, "operator", ep, "goal", "arm", "--joints", *map(str, TARGET), "--timeout", "120",
                   timeout=180)
        assert ok.returncode == 0 and "succeeded" in ok.stdout, ok.stdout + ok.stderr
        assert np.abs(truth.now() - np.asarray(TARGET)).max() < 0.02, truth.now()
    finally:
        observer.close()
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGINT)
        out = finish(p, 60)
    assert "ready:" in out, out


def test_bad_router_config_and_tls_files_are_one_line_errors(tmp_path: Path) -> None:
    missing = subprocess.run([*HILSIM, "router", "--config", str(tmp_path / "nope.json5")], capture_output=True,
                             text=True, cwd=REPO, timeout=60)
    assert missing.returncode == 2 and missing.stderr.strip().count("\n") == 0, missing.stderr
    assert "nope.json5: no such router config file" in missing.stderr
    broken = tmp_path / "router.json5"
    broken.write_text('{ mode: "router", transport: { link: { tls: { root_ca_certificate: "certs/ca.pem" } } } }')
    r = subprocess.run([*HILSIM, "router", "--config", str(broken)], capture_output=True, text=True, cwd=REPO,
                       timeout=60)
    assert r.returncode == 2 and "transport.link.tls.root_ca_certificate: file" in r.stderr, r.stderr
    env = {**os.environ, "HILSIM_TLS_ROOT_CA": str(tmp_path / "ca.pem"),
           "HILSIM_TLS_CERTIFICATE": str(tmp_path / "x.pem"), "HILSIM_TLS_PRIVATE_KEY": str(tmp_path / "x.key")}
    up = subprocess.run([*HILSIM, "up", "arm", "--router", "tls/127.0.0.1:1"], capture_output=True, text=True,
                        cwd=REPO, timeout=60, env=env)
    assert up.returncode == 2 and "zenoh.tls" in up.stderr and "does not exist" in up.stderr, up.stderr
    assert up.stderr.strip().count("\n") == 0, up.stderr
    env.pop("HILSIM_TLS_PRIVATE_KEY")
    echo = subprocess.run([*HILSIM, "topic", "list", "--duration", "0.1"], capture_output=True, text=True,
                          cwd=REPO, timeout=60, env=env)
    assert echo.returncode == 2 and "HILSIM_TLS_PRIVATE_KEY not set" in echo.stderr, echo.stderr
