"""Who sent what: announced writers, impostors, gaps, duplicates and reordering."""

from __future__ import annotations

import threading
from typing import Any

import pytest
import zenoh
from util import wait_until

from hilsim.core import msgs, transport
from hilsim.core.keys import Keys
from hilsim.core.provenance import Provenance, parse_writer_token
from hilsim.core.transport import Attachment
from hilsim.services.controller import ControllerService

KEY = "hilsim/arm/joint_commands"  # any string: the bookkeeping does not parse keys
KEY_ROS = Keys().topic("joint_commands")
A, B = b"A" * 16, b"B" * 16


def att(seq: int, gid: bytes = A) -> Attachment:
    return Attachment(seq, 0, gid)


def test_an_open_key_accepts_anything_and_counts_gaps() -> None:
    p = Provenance()
    assert p.check(KEY, None) == (None, 0)  # nobody announced this key: a tool may drive a service
    assert p.check(KEY, att(5)) == (None, 0)  # the first sample seen from a writer is no loss
    assert p.check(KEY, att(6)) == (None, 0)
    assert p.check(KEY, att(9)) == (None, 2)  # 7 and 8 never arrived
    assert p.check(KEY, att(1, B)) == (None, 0)  # writers are counted apart


def test_a_writers_id_on_an_open_key_it_never_announced_makes_no_loss() -> None:
    """A gid is its writer's graph token's hash, topic included: the planner's id on another (open) key is an
    insider's copy with numbers of its choosing. Delivered, but a hole in those numbers is no loss (CI: an
    injector's forged planner ids on joint_trajectory left one, and the recorder said 'lost 1 in lockstep')."""
    p = Provenance()
    p.announce("planner/joint_trajectory", A)
    assert p.check(KEY, att(2), b"two") == (None, 0)
    assert p.check(KEY, att(4), b"four") == (None, 0)  # 3 never came: the forger skipped it
    assert p.check(KEY, att(1, B)) == (None, 0) and p.check(KEY, att(3, B)) == (None, 1)  # a writer of its own: counted
    assert p.check("planner/joint_trajectory", att(1), b"a") == (None, 0)  # and on its own key, its gaps count
    assert p.check("planner/joint_trajectory", att(3), b"c") == (None, 1)


def test_only_a_true_duplicate_is_rejected_and_nothing_is_dropped_for_its_order() -> None:
    """The same number with the same payload again is a duplicate (rejected); a number behind the writer's
    newest is delivered, counted as suspect, and its writer's gaps are withdrawn from its losses."""
    p = Provenance()
    p.check(KEY, att(3), b"three")
    why, _ = p.check(KEY, att(3), b"three")
    assert why is not None and "duplicate" in why
    assert p.check(KEY, att(6), b"six") == (None, 2)  # 4 and 5 missing
    assert p.check(KEY, att(2), b"two") == (None, -2)  # delivered; suspect: the gaps are no longer said lost
    assert p.suspect[KEY] == 1 and p.contested(KEY) == 2
    assert p.check(KEY, att(7), b"seven") == (None, 0)  # and the stream goes on
    why, _ = p.check("0/*/joint_commands/x/RIHS01_y", att(1), b"x")  # a key expression, not a key
    assert why is not None and "wildcards" in why


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


@pytest.mark.parametrize("attack", ["next_number_first", "far_ahead", "plausible_jump", "replay_recent",
                                    "replay_old", "first_sample", "burst_ahead"])
def test_no_forged_or_replayed_sample_drops_a_genuine_one_or_makes_a_loss(attack: str) -> None:
    """A writer's real gid in forged samples, every way we know (docs/keys.md, "Suspect samples"): the
    writer's own samples are all delivered, a loss is never counted where none happened (the real one, 2
    samples, is counted unless the writer is contested, then withdrawn and said apart), and whatever did
    not fit the writer's sequence is counted as suspect. (The check before this one dropped every later
    genuine sample after one forged number far ahead: "out of order: sample 2656 after 12171".)"""
    clock = Clock()
    p = Provenance(clock=clock)
    p.announce(KEY, A)
    gaps = 0
    rejected = []

    def forge(seq: int, payload: bytes = b"forged") -> None:
        nonlocal gaps
        _, gap = p.check(KEY, att(seq), payload)
        gaps += gap

    def real(seqs: range, lost: set[int] = frozenset()) -> None:
        nonlocal gaps
        for s in seqs:
            clock.t += 0.001
            if s not in lost:
                why, gap = p.check(KEY, att(s), f"real {s}".encode())
                gaps += gap
                rejected.append(why)

    if attack == "first_sample":
        forge(50_000)  # before any of the writer's own
        real(range(1, 101), lost={40, 41})
    else:
        real(range(1, 51))
        if attack == "next_number_first":
            forge(51)  # the writer's next number, before the writer sends it
        elif attack == "far_ahead":
            forge(12_171)
        elif attack == "plausible_jump":
            forge(60)  # a jump the writer could have made: its 51..59 then fill it
        elif attack == "replay_recent":
            forge(30, b"real 30")  # a copy of a real sample: a duplicate
        elif attack == "replay_old":
            real(range(51, 2001))
            forge(10, b"real 10")  # older than the window: not provably a duplicate
        elif attack == "burst_ahead":
            for s in range(51, 5051):  # racing ahead of the writer, one number at a time
                forge(s)
        start = 2001 if attack == "replay_old" else 51
        real(range(start, start + 100), lost={start + 40, start + 41})
    assert rejected == [None] * len(rejected), [r for r in rejected if r]  # every genuine sample delivered
    contested = p.contested(KEY)
    if attack == "replay_recent":
        assert p.suspect[KEY] == 0 and gaps == 2  # rejected as a duplicate, nothing else changed
    else:
        assert p.suspect[KEY] >= 1, attack
        assert gaps in (0, 2) and gaps + contested >= 2, (attack, gaps, contested)  # never more than the real loss
        if gaps == 0:
            assert contested >= 2


def test_a_restricted_key_takes_only_announced_writers() -> None:
    p = Provenance(grace=0.0)
    p.announce(KEY, A)
    assert p.check(KEY, att(1)) == (None, 0)
    why, _ = p.check(KEY, att(1, B))
    assert why is not None and "not announced" in why
    why, _ = p.check(KEY, None)
    assert why is not None and "no attachment" in why
    p.announce(KEY, B)  # a second writer announces itself (e.g. a restarted service)
    assert p.check(KEY, att(1, B)) == (None, 0)
    p.withdraw(KEY, A)
    p.withdraw(KEY, B)
    why, _ = p.check(KEY, att(2, B))  # the key stays restricted when its writers are gone
    assert why is not None and "not announced" in why


def test_a_departed_writers_last_samples_are_still_its_own_for_a_moment() -> None:
    """A stopping service's token may overtake its last samples: they are accepted for the grace
    period (still checked for order), then its id is a stranger's."""
    now = [100.0]
    p = Provenance(grace=1.0, clock=lambda: now[0])
    p.announce(KEY, A)
    assert p.check(KEY, att(1)) == (None, 0)
    p.withdraw(KEY, A)
    now[0] += 0.5
    assert p.check(KEY, att(2)) == (None, 0)  # in flight when the token went
    why, _ = p.check(KEY, att(2))
    assert why is not None and "duplicate" in why
    now[0] += 1.0
    why, _ = p.check(KEY, att(3))
    assert why is not None and "not announced" in why


def test_writer_tokens_round_trip() -> None:
    """A publisher's graph token names the key it writes; its gid is the token's hash (rmw_zenoh)."""
    k = Keys("hilsim", "arm")
    for key in (k.topic("joint_commands"), k.clock):
        token, gid = k.writer_token(key)
        assert parse_writer_token(token) == (key, gid)
    node = "@ros2_lv/0/1/0/0/NN/%/%arm/tool"
    assert parse_writer_token(node) is None
    assert parse_writer_token(k.writer_token(KEY_ROS)[0].replace("/MP/", "/MS/")) is None  # a subscription
    assert parse_writer_token("hilsim/writers/zz/arm/x") is None
    assert parse_writer_token("hilsim/arm/alive/physics") is None


def test_a_running_service_rejects_impostors_and_counts_gaps(scenario: Any, session: zenoh.Session,
                                                             run_service: Any) -> None:
    """Over Zenoh: the controller takes joint_states only from the announced writer, counts a gap,
    rejects a duplicate, says why for each rejected sample, and delivers a sample out of its writer's order
    (counted as suspect in health, the gaps then withdrawn: the writer is contested)."""
    sc = scenario()
    keys = Keys.of(sc)
    key = keys.topic("joint_states")
    names = [f"joint_{i}" for i in range(1, 7)]
    cmds: list[int] = []
    got = threading.Event()

    def on_cmd(s: zenoh.Sample) -> None:
        cmds.append(msgs.ns_of(msgs.decode(msgs.JointState, s.payload.to_bytes()).header.stamp))
        got.set()

    sub = session.declare_subscriber(keys.topic("joint_commands"), on_cmd)
    pub = transport.publisher(session, key)
    token_key, gid = keys.writer_token(key)
    stranger = transport.new_gid()
    token = session.liveliness().declare_token(token_key)

    def send(k: int, seq: int, who: bytes | None) -> None:
        js = msgs.JointState(header=msgs.header(k * 1_000_000), name=names, position=[0.0] * 6, velocity=[0.0] * 6)
        kw = {} if who is None else {"attachment": transport.attachment_bytes(seq, who)}
        pub.put(msgs.encode(js), **kw)

    with run_service(ControllerService(sc)) as svc:
        assert wait_until(lambda: key in svc.provenance.restricted, 5)
        for k, seq in ((0, 1), (1, 2), (2, 5)):  # 3 and 4 lost on the way
            got.clear()
            send(k, seq, gid)
            assert got.wait(5)
        assert svc.seq_gaps[key] == 2
        send(3, 9, stranger)  # an impostor, well-formed
        send(3, 9, None)  # a sample without attachment
        send(2, 5, gid)  # a duplicate of the announced writer's last sample
        assert wait_until(lambda: svc.rejected[key] == 3, 5), dict(svc.rejected)
        assert cmds == [0, 1_000_000, 2_000_000]  # the controller answered only the real samples
        got.clear()
        send(3, 4, gid)  # one out of order: delivered, suspect
        assert got.wait(5) and cmds == [0, 1_000_000, 2_000_000, 3_000_000]
        assert wait_until(lambda: svc.provenance.suspect[key] == 1, 5)
        assert svc.seq_gaps[key] == 0 and svc.provenance.contested(key) == 1  # 3 still missing, not said lost
        h = {kv.key: kv.value for kv in svc.health().status[0].values}
        assert h["seq_gaps"] == "0" and h[f"rejected:{key}"] == "3" and h[f"suspect:{key}"] == "1"
    token.undeclare()
    sub.undeclare()


def test_a_key_nobody_subscribes_to_is_not_put_until_someone_does(scenario: Any, session: zenoh.Session,
                                                                  run_service: Any) -> None:
    """Pay only for what is consumed: the controller's reference, read by nobody, is counted but
    neither encoded nor put; a subscriber that appears mid-run (a ROS 2 node, a tool) receives the
    very next sample, its sequence number continuing the count."""
    sc = scenario()
    keys = Keys.of(sc)
    key, ref_key = keys.topic("joint_states"), keys.topic("controller/reference")
    names = [f"joint_{i}" for i in range(1, 7)]
    pub = transport.publisher(session, key)
    token_key, gid = keys.writer_token(key)
    token = session.liveliness().declare_token(token_key)
    seq = iter(range(1, 10_000))

    def send(k: int) -> None:
        js = msgs.JointState(header=msgs.header(k * 1_000_000), name=names, position=[0.0] * 6, velocity=[0.0] * 6)
        pub.put(msgs.encode(js), attachment=transport.attachment_bytes(next(seq), gid))

    class Counting:  # what reaches Zenoh's put
        def __init__(self, real: zenoh.Publisher) -> None:
            self.real, self.n = real, 0

        def put(self, *a: Any, **kw: Any) -> None:
            self.n += 1
            self.real.put(*a, **kw)

    got: list[int] = []
    with run_service(ControllerService(sc)) as svc:
        assert wait_until(lambda: key in svc.provenance.restricted, 5)
        ref = svc.ref_pub
        ref._pub = counting = Counting(ref._pub)
        for k in range(5):
            send(k)
        assert wait_until(lambda: svc.counts_out[ref_key] == 5, 5), dict(svc.counts_out)
        assert counting.n == 0 and not ref.matching  # counted as published, never put
        sub = session.declare_subscriber(
            ref_key, lambda s: got.append(transport.read_attachment(s).seq))  # type: ignore[union-attr]
        assert wait_until(lambda: ref.matching, 5)
        send(5)
        assert wait_until(lambda: got == [6], 5), got
        assert counting.n == 1
        sub.undeclare()
        assert wait_until(lambda: not ref.matching, 5)
    token.undeclare()
