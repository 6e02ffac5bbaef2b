"""How the command-line tools find a running simulation (hilsim.core.transport.tool_*)."""

from __future__ import annotations

import pytest

from hilsim.core import transport
from hilsim.core.keys import Keys


def test_tool_endpoints_and_prefix(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("HILSIM_ZENOH_CONNECT", raising=False)
    monkeypatch.delenv("HILSIM_PREFIX", raising=False)
    assert transport.tool_endpoints() == ["tcp/127.0.0.1:7447"]
    assert transport.tool_prefix() == "hilsim"
    monkeypatch.setenv("HILSIM_ZENOH_CONNECT", "tcp/192.0.2.1:7447, tcp/192.0.2.2:7447,")
    monkeypatch.setenv("HILSIM_PREFIX", "lab2")
    assert transport.tool_endpoints() == ["tcp/192.0.2.1:7447", "tcp/192.0.2.2:7447"]
    assert transport.tool_prefix() == "lab2"
    # the command line wins over the environment
    assert transport.tool_endpoints("tcp/127.0.0.1:9000") == ["tcp/127.0.0.1:9000"]
    assert transport.tool_prefix("mine") == "mine"


def test_wait_for_service_sees_liveliness(router: str) -> None:
    keys = Keys("hilsim", "arm")
    with transport.open_tool_session(router) as tool, transport.open_tool_session(router) as svc:
        assert not transport.wait_for_service(tool, keys, "controller", 0.2)
        token = svc.liveliness().declare_token(keys.alive("controller"))
        try:
            assert transport.wait_for_service(tool, keys, "controller", 5.0)
        finally:
            token.undeclare()
