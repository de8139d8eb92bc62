"""The kinds of run, registered once: what config.json's `kind` names, and the run's replay.

`northfinder replay` dispatches through :func:`kind_of` + :meth:`RunKind.replay`; each kind's replay
returns the same :class:`Replayed`. A run directory written before `kind` was recorded is a find.
The modules are named by import path and loaded on first use (a replay loads only its own kind).
"""

from __future__ import annotations

import importlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from northfinder.rundir import CONFIG


@dataclass
class Replayed:
    """A replay's outcome: the recomputed result (None: too little to compute one), whether the run
    was complete, and for a find how many positions it measured of how many planned."""

    result: dict[str, Any] | None
    complete: bool
    positions_measured: int | None = None
    positions_planned: int | None = None


@dataclass(frozen=True)
class RunKind:
    """One kind of run: its name in config.json and its module's replay function."""

    kind: str
    module: str
    replay_function: str
    label: str

    def replay(self, run_dir: str | Path, method: str | None = None) -> Replayed:
        """Recompute the run's result from its raw logs (`method`: a find's heading method)."""
        fn = getattr(importlib.import_module(self.module), self.replay_function)
        if self.kind == "find":
            out = fn(run_dir, method=method)
            return Replayed(out.result, out.complete, out.positions_measured, out.positions_planned)
        result, complete = fn(run_dir)
        return Replayed(result, complete)


KINDS: dict[str, RunKind] = {
    k.kind: k
    for k in (
        RunKind("find", "northfinder.runs.find", "replay", "find"),
        RunKind("align-swaying", "northfinder.runs.swaying", "replay_swaying_run", "align --mode swaying"),
        RunKind("align-gnss", "northfinder.runs.gnss", "replay_gnss_run", "align --mode gnss"),
    )
}


def kind_of(run_dir: str | Path) -> RunKind:
    """The kind config.json records; a find when it records none (or cannot be read: the find's
    replay then names what is missing)."""
    try:
        kind = str(json.loads((Path(run_dir) / CONFIG).read_text(encoding="utf-8")).get("kind", "find"))
    except (OSError, ValueError, AttributeError):
        kind = "find"
    return KINDS.get(kind, KINDS["find"])
