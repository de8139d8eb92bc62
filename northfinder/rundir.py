"""The run directory (IO only): its layout, session file names, writing and reading JSON and events.

Layout (file names are fixed so that `northfinder replay RUN_DIR` finds them)::

    config.json      the configuration used (bench tables, and the simulator's truth if simulated)
    imu.raw          the IMU's bytes exactly as they arrived (written by the Imu driver)
    can.asc          every CAN frame, python-can ASCII log (written by the Accelerometer driver)
    turntable.log    the stage's command transcript (written by the Turntable driver)
    events.jsonl     one JSON object a line: start, one per position (sample ranges), end/abort
    result.json      the result (docs/result-schema.md)
    report.png       the plots (northfinder.report)

A run resumed with `northfinder find --resume RUN_DIR` is a second *session*: its devices are
new streams (the IMU's sample counter and the CAN counter start again), so it writes its own
`imu-2.raw`, `can-2.asc`, `turntable-2.log` (session k: `-k`), and its `start` event says which;
replay decodes each session's logs for the position events that follow its start event.

What a run *means* lives elsewhere: dwell statistics in northfinder.estimators.means, result
assembly, log decoding and replay of a turntable find in northfinder.runs.find.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from northfinder.errors import InputError

IMU_RAW = "imu.raw"
CAN_LOG = "can.asc"
TRANSCRIPT = "turntable.log"
EVENTS = "events.jsonl"
CONFIG = "config.json"
RESULT = "result.json"
REPORT = "report.png"


def session_file(name: str, session: int) -> str:
    """`imu.raw` for session 1, `imu-2.raw` for session 2 (a resumed run), …"""
    if int(session) <= 1:
        return name
    stem, dot, suffix = name.partition(".")
    return f"{stem}-{int(session)}{dot}{suffix}"


class RunDir:
    """A run directory being written (or read back). Each write is flushed and fsynced.

    `session` (1, or k for the k-th `--resume`) picks the raw log names (session_file)."""

    def __init__(self, path: str | Path, *, create: bool = True, session: int = 1):
        self.path = Path(path)
        self.session = int(session)
        self.created = create and not self.path.exists()
        """True if this object made the directory (a failed start may then remove it again)."""
        if create:
            try:
                self.path.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                msg = f"--out {self.path}: cannot create the run directory ({exc.strerror})"
                raise InputError(msg) from None
        elif not self.path.is_dir():
            raise InputError(f"{self.path}: no such run directory")

    @classmethod
    def new_run(cls, path: str | Path, resume_hint: str = "") -> RunDir:
        """The directory of a new run (`--out`): made if missing; one that already holds a run (its
        events log) is refused — the second run's events would join the first's and its raw logs
        replace theirs, so neither could be replayed."""
        p = Path(path)
        if (p / EVENTS).exists():
            raise InputError(
                f"--out {p} already holds a run ({EVENTS}); give a new directory{resume_hint}"
            )
        rd = cls(p)
        rd.check_writable()
        return rd

    def check_writable(self) -> None:
        """Refuse, in one line, a directory this process cannot write into (read-only, not ours)
        before anything is started — not a traceback at the first file written."""
        probe = self.path / f".write-check-{os.getpid()}"
        try:
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as exc:
            raise InputError(
                f"--out {self.path}: cannot write into it ({exc.strerror}); give a writable directory"
            ) from None

    # -- paths -------------------------------------------------------------------------------
    def file(self, name: str) -> Path:
        return self.path / name

    @property
    def imu_raw_path(self) -> Path:
        return self.file(session_file(IMU_RAW, self.session))

    @property
    def can_log_path(self) -> Path:
        return self.file(session_file(CAN_LOG, self.session))

    @property
    def transcript_path(self) -> Path:
        return self.file(session_file(TRANSCRIPT, self.session))

    @property
    def report_path(self) -> Path:
        return self.file(REPORT)

    # -- writing -----------------------------------------------------------------------------
    def write_json(self, name: str, data: dict[str, Any]) -> Path:
        """Write a JSON file atomically (temp file + rename) so a reader never sees half of it."""
        target = self.file(name)
        tmp = target.with_suffix(target.suffix + ".tmp")
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(jsonable(data), fh, indent=2, allow_nan=False)
            fh.write("\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
        return target

    def log_event(self, event: dict[str, Any]) -> None:
        """Append one event line to events.jsonl and push it to disk."""
        with open(self.file(EVENTS), "a", encoding="utf-8") as fh:
            fh.write(json.dumps(jsonable(event), allow_nan=False) + "\n")
            fh.flush()
            os.fsync(fh.fileno())

    # -- reading -----------------------------------------------------------------------------
    def read_json(self, name: str) -> dict[str, Any]:
        try:
            return json.loads(self.file(name).read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputError(f"{self.path}: {name} is missing; not a northfinder run directory?") from None

    def events(self) -> list[dict[str, Any]]:
        """Every event; a torn last line (power cut mid-write) is ignored."""
        try:
            lines = self.file(EVENTS).read_text(encoding="utf-8").splitlines()
        except FileNotFoundError:
            raise InputError(f"{self.path}: {EVENTS} is missing; not a northfinder run directory?") from None
        out = []
        for line in lines:
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                continue
        return out


def jsonable(obj: Any) -> Any:
    """numpy scalars/arrays → Python; NaN/inf → None (JSON has no NaN)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return jsonable(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


