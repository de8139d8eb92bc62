"""The kinds of run, each registered once: its measure, compute, replay and history row.

A kind is what a run directory records (config.json's `kind`; a campaign directory is the one with
campaign.json) and the four functions that own it:

- `measure`: the live run (acquisition and saving; the CLI hands it its view),
- `compute`: the result function the live run and its replay share (so a replay equals the live
  result bit for bit),
- `replay`: recompute the result from the run directory's raw logs alone → :class:`Replayed`,
- `history_row`: the results history's row of a finished run directory (northfinder.history.rows).

`northfinder replay`, the results history (recording, `--rebuild`) and the campaign (its finds)
dispatch through :func:`kind_of` and :data:`KINDS`; nothing else keeps a list of kinds. The
functions are named by import path and loaded on first use, as the device models are
(devices/registry.py): a replay loads only its own kind, and this module — below the runs and the
history in the layers — imports neither.
"""

from __future__ import annotations

import importlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

CONFIG_JSON = "config.json"
CAMPAIGN_JSON = "campaign.json"


@dataclass
class Replayed:
    """A replay's outcome: the recomputed result (None: too little to compute one), whether the run
    was complete, and for a find how many positions it measured of how many planned."""

    result: dict[str, Any] | None
    complete: bool
    positions_measured: int | None = None
    positions_planned: int | None = None
    positions: list[dict[str, Any]] | None = None
    """A find's per-position means (result.json's `positions` rows), also when too few for a heading."""


def _resolve(target: str) -> Any:
    module, _, attr = target.partition(":")
    return getattr(importlib.import_module(module), attr)


@dataclass(frozen=True)
class RunKind:
    """One kind of run: its name, the file holding its live result (what a replay is compared with),
    and its four functions by import path ("module:function")."""

    kind: str
    result_file: str
    measure_at: str
    compute_at: str
    replay_at: str
    history_row_at: str

    @property
    def measure(self) -> Any:
        """The live run."""
        return _resolve(self.measure_at)

    @property
    def compute(self) -> Any:
        """The result function live and replay share."""
        return _resolve(self.compute_at)

    def replay(self, run_dir: str | Path, method: str | None = None) -> Replayed:
        """Recompute the run's result from its raw logs (`method`: a find's heading method)."""
        return _resolve(self.replay_at)(run_dir, method=method)

    def history_row(self, run_dir: Path, unit: str | None = None) -> dict[str, Any] | None:
        """The history row of a finished run directory (None: no complete result)."""
        return _resolve(self.history_row_at)(run_dir, unit)


KINDS: dict[str, RunKind] = {
    k.kind: k
    for k in (
        RunKind("find", "result.json",
                "northfinder.runs.find:run_find", "northfinder.runs.find:compute_result",
                "northfinder.runs.find:replayed", "northfinder.history.rows:find_row"),
        RunKind("align-swaying", "result.json",
                "northfinder.runs.swaying:acquire", "northfinder.runs.swaying:result_from_run",
                "northfinder.runs.swaying:replayed", "northfinder.history.rows:align_row"),
        RunKind("align-gnss", "result.json",
                "northfinder.runs.gnss_live:acquire", "northfinder.runs.gnss:result_from_run",
                "northfinder.runs.gnss:replayed", "northfinder.history.rows:align_row"),
        RunKind("campaign", CAMPAIGN_JSON,
                "northfinder.runs.campaign:run_campaign", "northfinder.runs.campaign:update_statistics",
                "northfinder.runs.campaign:replayed", "northfinder.history.rows:campaign_row"),
    )
}


def kind_of(run_dir: str | Path) -> RunKind:
    """The kind a run directory records: a campaign if it holds campaign.json, else config.json's
    `kind`; a find when it records none (or cannot be read: the find's replay then names what is
    missing)."""
    d = Path(run_dir)
    if (d / CAMPAIGN_JSON).exists():
        return KINDS["campaign"]
    try:
        kind = str(json.loads((d / CONFIG_JSON).read_text(encoding="utf-8")).get("kind", "find"))
    except (OSError, ValueError, AttributeError):
        kind = "find"
    return KINDS.get(kind, KINDS["find"])
