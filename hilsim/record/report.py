"""What the recorder says of its recording at the end: ``record_summary.json`` and its per-key lines.

Built from the recorder's counts (services/logger.py, which writes the file and prints the lines):
per key ``received``, ``recorded``, ``bagged`` (with a bag), ``rejected``, ``lost``, ``dropped``,
``before_first``, ``unannounced``, and where they apply ``duplicates``, ``after_stop``, ``key_subscribed``,
``suspect``, ``contested``, ``expected`` (docs/recording.md says what each means); a stopped recording's entry under
``hilsim.core.recording.STOPPED_ENTRY``. Reads and writes no key.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hilsim.core.recording import STOPPED_ENTRY


@dataclass
class Counts:
    """The recorder's counts per key at its end (each a copy, taken under its lock)."""

    received: Counter[str]
    recorded: Counter[str]
    bagged: Counter[str]
    rejected: Counter[str]
    lost: Counter[str]  # judged: no more than the writers say they published and did not deliver
    dropped: Counter[str]
    before_first: Counter[str]
    unannounced: Counter[str]
    duplicates: Counter[str]
    after_stop: Counter[str]
    suspect: Counter[str]
    contested: Counter[str]
    plain: set[str] = field(default_factory=set)  # keys subscribed one by one (batching)
    expected: set[str] = field(default_factory=set)  # latched keys the run publishes: each must come
    # samples in a service's batch of a key the key table does not let that service write: not recorded
    batch_refused: Counter[str] = field(default_factory=Counter)

    def keys(self) -> list[str]:
        return sorted(set(self.received) | set(self.recorded) | set(self.lost) | self.expected
                      | set(self.batch_refused))

    def missing(self) -> list[str]:
        """Expected keys of which nothing was recorded."""
        return sorted(k for k in self.expected if not self.recorded[k])


def summary(c: Counts, *, bag: bool, batching: bool, stopped_at: dict[str, Any] | None) -> dict[str, Any]:
    """``record_summary.json``'s content (``stopped_at``: what stopped the recording early, if it did)."""
    out: dict[str, Any] = {
        k: {
            "received": c.received[k],
            "recorded": c.recorded[k],
            **({"bagged": c.bagged[k]} if bag else {}),
            "rejected": c.rejected[k],
            "lost": c.lost[k],
            "dropped": c.dropped[k],
            "before_first": c.before_first[k],
            "unannounced": c.unannounced[k],
            **({"duplicates": c.duplicates[k]} if batching or c.duplicates[k] else {}),
            **({"after_stop": c.after_stop[k]} if stopped_at is not None else {}),
            # batching: a key the recorder subscribed one by one for a writer no batch covers (a ROS 2
            # node, a tool, another run's bridge): its before_first were published before that subscription
            **({"key_subscribed": True} if k in c.plain else {}),
            # samples that do not fit their writer's sequence, and gaps not counted as lost for it
            **({"suspect": c.suspect[k]} if c.suspect[k] else {}),
            **({"contested": c.contested[k]} if c.contested[k] else {}),
            # a latched key the run publishes once (/tf_static, robot_description): the summary says if it is missing
            **({"expected": True} if k in c.expected else {}),
            # in a batch of a service the key table does not let write it: not recorded (docs/recording.md)
            **({"batch_refused": c.batch_refused[k]} if c.batch_refused[k] else {}),
        }
        for k in c.keys()
    }
    if stopped_at is not None:  # not a key: what stopped the recording (hilsim.core.recording.read_counts)
        out[STOPPED_ENTRY] = {**stopped_at, "after_stop": sum(c.after_stop.values())}
    return out


def lines(c: Counts, *, rrd: Path, bag_dir: Path | None, clock: str, stopped_at: dict[str, Any] | None) -> list[str]:
    """The lines the recorder prints at its end: one per key, the totals, what was not recorded and why."""
    keys = c.keys()
    total_in, total_rec, total_lost = sum(c.received.values()), sum(c.recorded.values()), sum(c.lost.values())
    out = [
        f"recorded {k}: received {c.received[k]} recorded {c.recorded[k]}"
        + (f" bagged {c.bagged[k]}" if bag_dir else "") + (f" lost {c.lost[k]}" if c.lost[k] else "")
        for k in keys
    ]
    out.append(
        f"recorded total: received {total_in} recorded {total_rec} rejected {sum(c.rejected.values())} "
        f"lost {total_lost} in {len(keys)} keys -> {rrd}"
        + (f"; bagged {sum(c.bagged.values())} -> {bag_dir}" if bag_dir else "")
    )
    early = {k: c.before_first[k] for k in sorted(c.plain) if c.before_first[k]}
    if early:
        out.append(f"not recorded: {sum(early.values())} samples their writers published before the recorder's "
                   "subscription reached them (logger.batch): " + ", ".join(f"{k} {n}" for k, n in early.items()))
    refused = {k: n for k, n in sorted(c.batch_refused.items()) if n}
    if refused:
        out.append(f"not recorded: {sum(refused.values())} samples in batches of services the key table does not let "
                   "write them (batch_refused): " + ", ".join(f"{k} {n}" for k, n in refused.items()))
    if stopped_at is not None:
        out.append(f"recording stopped at sim time {stopped_at.get('sim_time')} s: {stopped_at.get('reason')}; "
                   f"{sum(c.after_stop.values())} samples after it not recorded")
    if c.missing():
        out.append(f"expected but never received: {', '.join(c.missing())} (latched: put once at its writer's start)")
    if total_lost:
        n_drop = sum(c.dropped.values())
        out.append(f"lost {total_lost} samples ({clock}: the recorder could not keep up): "
                   f"{total_lost - n_drop} in transport, {n_drop} dropped by the logger (queue full)")
    return out
