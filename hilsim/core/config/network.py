"""Where a process meets the others: Zenoh (peer or client, TLS, user and password, guests), the TLS identity
from the environment, and where the simulation sits in the ROS 2 graph (``ros2:``)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator

from hilsim.core.config.base import _Model
from hilsim.core.config.errors import ConfigError


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
