"""Rerun recordings: analytics switch, finding and opening recordings, checking their contents.

Rerun's SDK and viewer send anonymous usage analytics unless their config file says no. hilsim
never touches the user's own ``~/.config/rerun``: every process hilsim starts that loads rerun
(the logger, the viewer spawned by ``hilsim view``, ``rerun rrd …`` checks) gets
``XDG_CONFIG_HOME`` pointing at a hilsim-owned directory (``~/.cache/hilsim/rerun-config``)
whose ``rerun/analytics.json`` has ``analytics_enabled: false``. Check it with
``XDG_CONFIG_HOME=~/.cache/hilsim/rerun-config rerun analytics config``.

Nothing here imports rerun at module level, so importing this module changes nothing;
:func:`disable_analytics` must run before ``import rerun`` in a process that records.

    hilsim view [RRD] [--runs DIR]     open the viewer on RRD, or on the newest <DIR>/*/recording.rrd
                                       (a run's recording.rrd or directory: every part of the recording)

A recorder killed with SIGKILL cannot write the RRD footer (Rerun writes it when the file is
closed), so ``rerun rrd verify`` refuses the file although every message in it is whole up to
the recorder's last flush (``services/logger.py`` flushes twice a second).
:func:`recover_rrd` rewrites such a file with ``rerun rrd merge`` into a complete one, checks
that it holds every row of the original and passes ``rerun rrd verify``, and only then replaces
it; ``hilsim up`` does so for the recording of a recorder that died. A recorder restarted by
``hilsim up`` records the rest of the run in ``recording.restart-<n>.rrd`` (:func:`part_name`).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

RECORDING_NAME = "recording.rrd"
SUMMARY_NAME = "record_summary.json"
# an entry of record_summary.json that is not a key: why and when the recorder stopped recording
# (logger.max_size, logger.min_free), present only then; read_counts() leaves it out of the counts
STOPPED_ENTRY = "_recording_stopped"


def read_counts(path: Path) -> tuple[dict[str, dict[str, int]], dict[str, Any] | None]:
    """``record_summary.json`` (a run directory or the file): the counts per key, and what stopped the
    recording early (its reason, sim time, bytes), or None if it went on to the run's end."""
    p = path / SUMMARY_NAME if path.is_dir() else path
    data = json.loads(p.read_text())
    stopped = data.pop(STOPPED_ENTRY, None)
    return data, stopped


class RecordingError(RuntimeError):
    """A recording that cannot be found, opened or verified; the message is one line (plus tool output)."""


# ---------------------------------------------------------------- analytics off
def _config_home() -> Path:
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return cache / "hilsim" / "rerun-config"


def _analytics_config(home: Path) -> dict[str, object]:
    # rerun refuses (and re-enables analytics) if any of these fields is missing.
    return {
        "analytics_enabled": False,
        "analytics_id": "00000000000000000000000000000000",
        "metadata": {},
        "config_file_path": str(home / "rerun" / "analytics.json"),
        "data_dir_path": str(home / "analytics-data"),
    }


def _write_config(home: Path) -> None:
    path = home / "rerun" / "analytics.json"
    want = _analytics_config(home)
    try:
        if json.loads(path.read_text()) == want:
            return
    except (OSError, ValueError):
        pass
    path.parent.mkdir(parents=True, exist_ok=True)
    # Atomic replace: several hilsim processes may start at once.
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".analytics-", suffix=".json")
    with os.fdopen(fd, "w") as f:
        json.dump(want, f)
    os.replace(tmp, path)


def rerun_config_home() -> Path:
    """The hilsim-owned XDG_CONFIG_HOME for rerun processes, created with analytics off."""
    home = _config_home()
    try:
        _write_config(home)
    except OSError:
        # Read-only home (containers): fall back to a per-user temporary directory.
        home = Path(tempfile.gettempdir()) / f"hilsim-{os.getuid()}" / "rerun-config"
        _write_config(home)
    return home


def rerun_env() -> dict[str, str]:
    """Environment additions for any child process that loads rerun (SDK or viewer)."""
    return {"XDG_CONFIG_HOME": str(rerun_config_home())}


def disable_analytics() -> None:
    """Turn rerun analytics off for this process; call before ``import rerun``."""
    os.environ.update(rerun_env())


# ---------------------------------------------------------------- the rerun executable
def import_rerun() -> Any:
    """The ``rerun`` module, imported only after its analytics were turned off (for code that
    logs to Rerun lazily, e.g. the scene's static geometry)."""
    disable_analytics()
    import rerun

    return rerun


def rerun_executable() -> str:
    """Path of the ``rerun`` CLI of this environment: rerun_cli's binary itself where it is installed (the
    ``rerun`` script beside the interpreter is a Python wrapper that starts it as a child: two processes, and
    the binary left behind when the wrapper is killed), else the script beside the interpreter, else PATH's."""
    try:
        import rerun_cli

        exe = Path(rerun_cli.__file__).parent / "rerun"
        if exe.is_file() and os.access(exe, os.X_OK):
            return str(exe)
    except ImportError:
        pass
    here = Path(sys.executable).parent / "rerun"
    if here.is_file() and os.access(here, os.X_OK):
        return str(here)
    found = shutil.which("rerun")
    if found:
        return found
    raise RecordingError("the rerun executable was not found (install rerun-sdk in this environment)")


def _run_rerun(args: list[str], timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, **rerun_env()}
    return subprocess.run(
        [rerun_executable(), *args], env=env, capture_output=True, text=True, timeout=timeout, check=False
    )


# ---------------------------------------------------------------- checking recordings
def verify_rrd(path: str | Path) -> None:
    """Run ``rerun rrd verify``; raise :class:`RecordingError` with its output if the file is not valid."""
    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"{p}: no such recording")
    r = _run_rerun(["rrd", "verify", str(p)])
    if r.returncode != 0:
        out = (r.stdout + r.stderr).strip()
        raise RecordingError(f"{p}: rerun rrd verify failed (exit {r.returncode}):\n{out}")


def entity_rows(path: str | Path) -> dict[str, int]:
    """Rows stored per entity path (static rows included) of the first recording in an .rrd file."""
    return contents(path).rows


CLOCK_ENTITY = "/clock"  # where the recorder puts <prefix>/clock: how far sim time got


@dataclass
class Contents:
    """What a recording holds: rows per entity path and each one's latest ``sim_time`` (ns)."""

    rows: dict[str, int]
    last_ns: dict[str, int]

    @property
    def last_sim_ns(self) -> int | None:
        """How far the recording goes in sim time: its clock's latest (other entities, e.g. a
        planned path, can carry stamps of the future), else the latest of any entity."""
        if CLOCK_ENTITY in self.last_ns:
            return self.last_ns[CLOCK_ENTITY]
        return max(self.last_ns.values(), default=None)


def contents(path: str | Path) -> Contents:
    """Read a recording back with Rerun's Python API: a file, or a run directory (every part of its
    recording, :func:`recording_parts`, rows summed); a file without a footer (its writer was
    killed) is read by scanning it, as far as its messages are whole."""
    disable_analytics()
    import pyarrow.compute as pc
    from rerun.chunk import RrdReader  # experimental API of rerun 0.41

    p = Path(path)
    files = recording_files(p) if p.is_dir() else [p]
    if not p.exists():
        raise RecordingError(f"{p}: no such recording")
    rows: Counter[str] = Counter()
    last: dict[str, int] = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no footer": expected of a killed recorder's file
        chunks = (c for f in files for c in RrdReader(f).stream().to_chunks())
        for chunk in chunks:
            rows[chunk.entity_path] += chunk.num_rows
            if "sim_time" in chunk.timeline_names and chunk.num_rows:
                t = pc.max(chunk.to_record_batch().column("sim_time").cast("int64")).as_py()
                if t is not None:
                    last[chunk.entity_path] = max(last.get(chunk.entity_path, t), t)
    return Contents(dict(rows), last)


def part_name(attempt: int) -> str:
    """The file a recorder restarted for the ``attempt``-th time records to, in the run directory."""
    return f"recording.restart-{attempt}.rrd"


def split_name(first: str | Path, index: int) -> Path:
    """The ``index``-th file (1, 2, …) a recorder writes on in once ``first`` (``recording.rrd``, or a
    restarted recorder's ``recording.restart-<n>.rrd``) reached ``logger.max_rrd_size`` or
    ``max_rrd_duration``: ``recording.part-<index>.rrd`` (``recording.restart-<n>.part-<index>.rrd``)."""
    p = Path(first)
    return p.with_name(f"{p.stem}.part-{index}{p.suffix}")


# recording.rrd, recording.part-<k>.rrd, recording.restart-<n>.rrd, recording.restart-<n>.part-<k>.rrd
_PART = re.compile(r"recording(?:\.restart-(\d+))?(?:\.part-(\d+))?\.rrd")


def recording_parts(run_dir: str | Path) -> list[Path]:
    """A run's recording files in order: ``recording.rrd`` and the files it was split into
    (``recording.part-1.rrd``, …), then each restarted recorder's (:func:`part_name`, :func:`split_name`).
    They are one Rerun recording per recorder process (one recording id): Rerun's viewer opens them
    together as one (``rerun recording*.rrd``, ``hilsim view RUN``)."""
    d = Path(run_dir)
    found = []
    for p in d.glob("recording*.rrd"):
        m = _PART.fullmatch(p.name)
        if m and p.is_file():
            found.append((int(m[1] or 0), int(m[2] or 0), p))
    return [p for *_, p in sorted(found)]


def recording_files(path: str | Path) -> list[Path]:
    """The files of the recording ``path`` names: a run directory, or its ``recording.rrd``, stands for
    every part of the run's recording (:func:`recording_parts`); any other file is itself."""
    p = Path(path)
    if p.is_dir():
        files = recording_parts(p)
        if not files:
            raise RecordingError(f"{p}: no recording ({p / RECORDING_NAME} does not exist)")
        return files
    if not p.is_file():
        raise RecordingError(f"{p}: no such recording")
    return recording_parts(p.parent) if p.name == RECORDING_NAME else [p]


def _printed_rows(path: Path) -> Counter[str]:
    """Rows per entity path as ``rerun rrd print`` lists the chunks of a file."""
    r = _run_rerun(["rrd", "print", str(path)])
    if r.returncode != 0:
        raise RecordingError(f"{path}: rerun rrd print failed (exit {r.returncode}):\n{(r.stdout + r.stderr).strip()}")
    rows: Counter[str] = Counter()
    for m in re.finditer(r"^Chunk\(\S+\) with (\d+) rows .*? - (\S+) - ", r.stdout, re.M):
        rows[m[2]] += int(m[1])
    return rows


def recover_rrd(path: str | Path) -> bool:
    """Make a recording whose writer was killed complete again (see the module docstring).

    Returns False if it was complete already, True if it was rewritten; raises
    :class:`RecordingError` if its messages cannot be read, or the rewrite loses a row (the
    original is then left as it is)."""
    p = Path(path)
    try:
        verify_rrd(p)
        return False
    except RecordingError:
        pass
    r = _run_rerun(["rrd", "verify", "--check-footers", "false", str(p)])
    if r.returncode != 0:
        raise RecordingError(f"{p}: unreadable, even without its footer:\n{(r.stdout + r.stderr).strip()}")
    tmp = p.with_name(p.name + ".recovering")
    r = _run_rerun(["rrd", "merge", str(p), "-o", str(tmp)])
    try:
        if r.returncode != 0:
            raise RecordingError(f"{p}: rerun rrd merge failed (exit {r.returncode}):\n{(r.stdout + r.stderr).strip()}")
        verify_rrd(tmp)
        # Rerun's CLI reads up to the last whole message (its Python reader refuses a cut one)
        before, after = _printed_rows(p), _printed_rows(tmp)
        if before != after:
            raise RecordingError(f"{p}: the rewritten recording lacks rows ({sum(after.values())} of "
                                 f"{sum(before.values())}); the original is kept")
        os.replace(tmp, p)
    finally:
        tmp.unlink(missing_ok=True)
    return True


def entity_paths(path: str | Path) -> list[str]:
    """Sorted entity paths stored in a recording."""
    return sorted(entity_rows(path))


# ---------------------------------------------------------------- finding and viewing
def latest_recording(runs_dir: str | Path) -> Path:
    """The newest ``<runs_dir>/*/recording.rrd`` (by modification time)."""
    d = Path(runs_dir)
    if not d.is_dir():
        raise RecordingError(f"no recordings: directory {d} does not exist (run `hilsim up arm` first)")
    found = [p for p in d.glob(f"*/{RECORDING_NAME}") if p.is_file()]
    if not found:
        raise RecordingError(f"no recordings in {d} (expected {d}/<run>/{RECORDING_NAME}; run `hilsim up arm` first)")
    return max(found, key=lambda p: (p.stat().st_mtime, str(p)))


def has_display() -> bool:
    """Whether a window can be opened here (an X or Wayland display)."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def cmd_view(args: argparse.Namespace) -> int:
    """``hilsim view [RRD] [--runs DIR]``: open the Rerun viewer on a recording."""
    try:
        rrd = Path(args.rrd) if args.rrd else latest_recording(args.runs)
        # a split recording (logger.max_rrd_size, max_rrd_duration): every part, which the viewer opens as one
        files = recording_files(rrd)
        exe = rerun_executable()
    except RecordingError as e:
        print(f"hilsim view: {e}", file=sys.stderr)
        return 1
    home = rerun_config_home()
    # --bind: the viewer's gRPC server listens on loopback only.
    argv = [exe, "--bind", "127.0.0.1", *map(str, files)]
    command = f"XDG_CONFIG_HOME={home} " + " ".join(argv)
    if not has_display():
        print(
            f"hilsim view: no display (DISPLAY/WAYLAND_DISPLAY unset); recording: {rrd}\n"
            f"open it on a machine with a display: {command}",
            file=sys.stderr,
        )
        return 1
    print(f"opening {rrd}" + (f" and {len(files) - 1} more parts of it" if len(files) > 1 else ""), file=sys.stderr)
    env = {**os.environ, "XDG_CONFIG_HOME": str(home)}
    try:
        return subprocess.call(argv, env=env)
    except KeyboardInterrupt:
        return 130
