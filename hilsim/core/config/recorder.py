"""The ``logger:`` section: what the recorder records, where, its bag, batches, splits and limits, and its
live streams (Rerun's web viewer, Foxglove)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import Field, field_validator

from hilsim.core.config.base import _Model, parse_bytes


class LiveConfig(_Model):
    """The recorder's live stream to Rerun's web viewer (``hilsim up --view``; hilsim.record.live)."""

    enabled: bool = Field(False, description="stream the recording live to Rerun's bundled web viewer while the run "
                          "goes on (the address in <run dir>/live.json; docs/recording.md, \"Watch it live\")")
    host: str = Field("127.0.0.1", description="the address the viewer listens on (loopback; another one asks a "
                      "token in the viewer's URL)")
    port: int = Field(0, ge=0, le=65535, description="the viewer page's port (0: a free one)")
    from_start: bool = Field(False, description="stream from the run's start, watched or not (a viewer joining late "
                             "sees the whole run); false: from when a viewer first opens the page or `hilsim view "
                             "--live` joins, so a run nobody watches costs nothing")
    wait: float = Field(0.0, ge=0, description="seconds a run with a task waits for a viewer to join before its "
                        "physics starts (0: it does not wait); `hilsim up --view` waits 120 (`--view-wait S`)")


class FoxgloveConfig(_Model):
    """The recorder's samples on a Foxglove WebSocket server (``hilsim up --foxglove``; hilsim.record.foxglove_live)."""

    enabled: bool = Field(False, description="serve every recorded key's samples (raw CDR, ros2msg schemas) over "
                          "Foxglove's WebSocket protocol while the run goes on")
    host: str = Field("127.0.0.1", description="the address the server listens on (loopback)")
    port: int = Field(8765, ge=0, le=65535, description="its port (0: a free one)")


class LoggerConfig(_Model):
    enabled: bool = Field(True, description="false: no recorder in the run (as `hilsim up --no-logger`)")
    out_dir: Path = Path("runs")
    run_dir: Path | None = Field(None, description="write here instead of <out_dir>/<timestamp> (set by `hilsim up`)")
    record: list[str] = Field(default_factory=lambda: ["**"],
                              description="key expressions under <domain id>/, e.g. arm/** (hilsim.core.keys)")
    bag: bool = Field(True, description="also write <run dir>/bag/, a rosbag2 bag (MCAP) of every sample's raw CDR "
                      "(docs/recording.md)")
    batch: int = Field(256, ge=0, le=65535, description="samples per batch the run's services send the recorder on "
                       "one key each instead of every sample on its own key; writers outside them (ROS 2 nodes, "
                       "tools, bridges of other runs) are subscribed key by key from their publisher tokens (0: off, "
                       "the recorder subscribes to every key; docs/recording.md)")
    batch_max_age_ms: float = Field(50.0, gt=0, le=10_000, description="a batch not full is sent when its first "
                                    "sample is this old (wall ms), so a slow key's samples do not wait")
    max_bag_size: int = Field(0, ge=0, description="split the bag: a new file once the current one holds this many "
                              "bytes (as rosbag2's --max-bag-size; 0: no split by size; also '500MB', '2GiB')")
    max_bag_duration: float = Field(0.0, ge=0, description="split the bag: a new file once the current one spans "
                                    "this many seconds of receive time (as rosbag2's --max-bag-duration; 0: none)")
    max_rrd_size: int = Field(0, ge=0, description="split the Rerun recording: a new file (recording.part-1.rrd, "
                              "…) once the current one holds this many bytes, checked at each flush (twice a "
                              "second); the files are one recording, opened together by Rerun's viewer (0: no "
                              "split by size; also '500MB'; hilsim up --interactive: 500MB unless set)")
    max_rrd_duration: float = Field(0.0, ge=0, description="split the Rerun recording: a new file once the current "
                                    "one spans this many seconds of wall time (0: none)")
    max_size: int = Field(0, ge=0, description="cap on the run's recording (recording.rrd and bag/ together, "
                          "bytes; '2GB' too): the recorder stops recording there and the run goes on (0: no cap)")
    max_loss: float = Field(0.05, ge=0, le=1, description="realtime: the largest fraction of the published samples "
                            "the recording may miss (lost in transport, dropped by the recorder, never reached it); "
                            "more fails the run, 'result: FAILED (recording lost N %)' (1: never; hilsim up "
                            "--allow-loss). Lockstep loses nothing, whatever this says")
    min_free: int = Field(500 * 1000**2, ge=0, description="the recorder stops recording (the run goes on) before "
                          "the free space of the run directory's file system falls below this many bytes ('1GB' "
                          "too; 0: only a full disk stops it)")
    live: LiveConfig = Field(default_factory=LiveConfig)
    foxglove: FoxgloveConfig = Field(default_factory=FoxgloveConfig)

    @field_validator("max_bag_size", "max_rrd_size", "max_size", "min_free", mode="before")
    @classmethod
    def _bytes(cls, v: Any) -> Any:
        return parse_bytes(v) if isinstance(v, str) else v
