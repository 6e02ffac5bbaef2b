"""Latched (transient-local) topics are recorded every time, whatever the order in which the recorder
and their publisher come up: ``/tf_static`` and ``/<robot>/robot_description`` are put once, at the
publisher's start, and a recorder that comes before, after or while it starts still gets them
(rmw_zenoh's transient-local: a Zenoh advanced publisher's cache, queried again by the recorder until
the sample came: :mod:`hilsim.record.routes`). One it was told to expect and never got is said."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh

from hilsim.core import msgs
from hilsim.core.keys import Keys
from hilsim.core.service import Service
from hilsim.record.routes import KeyRoutes


class LatchedWriter(Service):
    """Physics' latched part alone: puts /tf_static and robot_description once in its setup."""

    name = "physics"

    def setup(self) -> None:
        t = msgs.TransformStamped(header=msgs.header(0, "world"), child_frame_id="base_link")
        self.publisher(self.keys.tf_static, latched=True).put(msgs.TFMessage(transforms=[t]))
        self.publisher(self.keys.topic("robot_description"), latched=True).put(msgs.String(data="<robot name='arm'/>"))


def _counts(run_dir: Path) -> dict[str, Any]:
    return json.loads((run_dir / "record_summary.json").read_text())


class _Token:
    """What the routes read of a liveliness sample."""

    def __init__(self, key: str, kind: zenoh.SampleKind = zenoh.SampleKind.PUT) -> None:
        self.key_expr, self.kind = key, kind


def test_a_batching_token_seen_after_the_latched_writers_keeps_their_subscription(
        scenario: Any, run_service: Any, session: zenoh.Session) -> None:
    """The race that lost /tf_static: the recorder saw physics' latched publishers (and asked their caches)
    before the token saying physics batches; dropping those subscriptions then, as for any key a batch
    covers, lost the sample whenever the batch had gone out before the recorder listened."""
    sc = scenario("arm", {"logger.batch": 256})
    keys = Keys.of(sc)
    writer = LatchedWriter(sc)
    got: list[str] = []
    with run_service(writer):
        # both publishers' tokens: declared in its setup, they reach the router a moment later (asked too soon,
        # one was missing in about half the runs, on main too)
        deadline = time.monotonic() + 10
        while True:
            tokens = [str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/**", timeout=2.0) if r.ok]
            latched = [t for t in tokens if "/MP/" in t and ("tf_static" in t or "robot_description" in t)]
            if len(latched) == 2 or time.monotonic() > deadline:
                break
            time.sleep(0.1)
        assert len(latched) == 2, tokens
        routes = KeyRoutes(keys, ["**"], batching=True)
        routes._session, routes._real = session, session
        routes._on_sample = lambda s: got.append(str(s.key_expr))
        for t in latched:
            routes._on_writer_token(_Token(t))
        routes._on_batch_token(_Token(writer.keys.batch(writer._zid, writer._node_id, writer.name)))
        wanted = {keys.tf_static, keys.topic("robot_description")}
        assert set(routes.key_subs) == wanted and set(routes.latched) == wanted
        deadline = time.monotonic() + 10
        while set(got) != wanted and time.monotonic() < deadline:
            time.sleep(0.05)
        assert set(got) == wanted, got
        # asked again only while nothing came
        for k in got:
            routes.got(k)
        routes.latched = dict.fromkeys(routes.latched, 0.0)
        assert routes.ask_again() == [] and routes.missing_latched() == []
        for d in routes.close():
            d.undeclare()


def test_an_expected_latched_topic_that_never_came_is_said(scenario: Any, run_service: Any, tmp_path: Path,
                                                           capsys: Any) -> None:
    """A run whose physics has a URDF publishes /tf_static and robot_description: a recorder that got neither
    lists both as expected with nothing received, and says so."""
    from hilsim.services.logger import LoggerService

    run_dir = tmp_path / "run"
    sc = scenario("arm", {"logger.run_dir": str(run_dir)})
    keys = Keys.of(sc)
    with run_service(LoggerService(sc)):
        time.sleep(0.3)
    counts = _counts(run_dir)
    for key in (keys.tf_static, keys.topic("robot_description")):
        assert counts[key]["expected"] is True and counts[key]["received"] == 0, counts.get(key)
    assert "expected but never received: " in capsys.readouterr().out


@pytest.mark.parametrize("batch", [256, 0], ids=["batches", "per-key"])
def test_latched_topics_are_recorded_whatever_the_order(scenario: Any, run_service: Any, tmp_path: Path,
                                                         batch: int) -> None:
    from hilsim.services.logger import LoggerService

    # the recorder's start against the publisher's: long before, just before, together, just after, long after
    offsets = [-1.0, -0.05, -0.01, 0.0, 0.0, 0.01, 0.05, 1.0]
    missing = []
    for i, lead in enumerate(offsets):
        run_dir = tmp_path / f"run{i}"
        sc = scenario("arm", {"logger.run_dir": str(run_dir), "logger.batch": batch})
        keys = Keys.of(sc)
        logger, writer = LoggerService(sc), LatchedWriter(sc)
        first, second = (run_service(logger), run_service(writer)) if lead <= 0 else \
            (run_service(writer), run_service(logger))
        started = threading.Event()
        with first:
            time.sleep(abs(lead))
            with second:
                started.set()
                time.sleep(0.5)  # long enough for a cache query, short of the recorder's retries
            # the writer stopped first: its cache is gone, what the recorder has is all it gets
        counts = _counts(run_dir)
        for key in (keys.tf_static, keys.topic("robot_description")):
            if counts.get(key, {}).get("received") != 1 or not counts[key].get("expected"):
                missing.append((lead, key, counts.get(key)))
    assert not missing, missing


def test_a_latched_cache_that_gave_nothing_is_asked_again_ever_less_often(monkeypatch: Any, scenario: Any) -> None:
    """An action's status is transient-local but put only once a goal comes: its cache is asked again after
    1 s, then 2, 4, … at most 30 s apart (each ask is a new subscription: at 1 s for a whole run it cost the
    realtime recorder a tenth of its time), and never again once a sample came."""
    from hilsim.record import routes as routes_mod

    now = [100.0]
    monkeypatch.setattr(routes_mod.time, "monotonic", lambda: now[0])
    routes = KeyRoutes(Keys.of(scenario("arm")), ["**"], batching=True)
    routes._subscribe_key = lambda key, latched: _Undeclarable()  # type: ignore[method-assign]
    routes.latched = {"k": now[0]}
    asks = []
    for _ in range(1200):  # 10 minutes in 0.5 s steps
        now[0] += 0.5
        if routes.ask_again():
            asks.append(now[0] - 100.0)
    gaps = [b - a for a, b in zip([0.0, *asks], asks, strict=False)]
    assert gaps[:6] == [1.0, 2.0, 4.0, 8.0, 16.0, 30.0], gaps
    assert set(gaps[5:]) == {30.0}, gaps
    routes.got("k")
    now[0] += 100
    assert routes.ask_again() == []
    # a key whose every writer sends batches is never asked again: its sample comes in the batch
    node, other = ("z1", "n1"), ("z2", "n2")
    routes.latched["b"] = now[0]
    routes.plain["b"] = {b"g1": node}
    routes.batching_nodes.add(node)
    now[0] += 60
    assert routes.ask_again() == []
    routes.plain["b"][b"g2"] = other  # a writer that does not (a ROS 2 node): asked again
    assert routes.ask_again() == ["b"]


class _Undeclarable:
    def undeclare(self) -> None:
        pass
