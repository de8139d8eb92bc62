"""A repeatability campaign: N finds in a row at each of one or more base headings (steps).

Each find is a complete run directory `stepK-runNN` under the campaign directory, made by the
find kind's own measure and replayed by its own replay (northfinder.runkinds: the campaign
dispatches to the find through the run-kind registry; it builds the find's request). campaign.json is the
campaign's state: written atomically at the start and after every find, it lists the finds done,
so `--resume` runs exactly the missing ones — none repeated, none lost. A find that was stopped or
failed is moved aside (`stepK-runNN.failed-A`) and measured again; a find that finished but was not
yet listed (killed between the two writes) is adopted as it is.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from northfinder.errors import InputError, NorthfinderError, RunAborted
from northfinder.estimators.campaign_stats import deviation_deg, method_statistics, step_statistics
from northfinder.history import record_or_warn
from northfinder.runkinds import CAMPAIGN_JSON, KINDS, Replayed
from northfinder.runs.base import now_utc
from northfinder.runs.find import FindRequest
from northfinder.runs.find_pace import AUTO

SCHEMA = "northfinder.campaign/1"
SEED_STRIDE = 1000
"""A simulated find's seed is seed + index + SEED_STRIDE·attempt: every find (and every retry of a
stopped one) draws its own sensor noise, and the same campaign plan draws the same noise again."""

FindRunner = Callable[[FindRequest, Path], None]
"""Runs one find (the find kind's measure) and writes its summary to the given path."""


def run_name(step: int, repeat: int) -> str:
    return f"step{step + 1}-run{repeat + 1:02d}"


def planned(plan: dict[str, Any]) -> list[tuple[int, int, int]]:
    """(index, step, repeat) of every find of the plan, in the order they are measured."""
    n = int(plan["repeat"])
    return [(s * n + r, s, r) for s in range(len(plan["steps"])) for r in range(n)]


def write_state(cdir: Path, state: dict[str, Any]) -> None:
    """campaign.json atomically (temp file, fsync, rename): a reader or a resume never sees half."""
    tmp = cdir / (CAMPAIGN_JSON + ".tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(state, fh, indent=2, allow_nan=False)
        fh.write("\n")
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, cdir / CAMPAIGN_JSON)


def read_state(cdir: Path, what: str = "--resume") -> dict[str, Any]:
    """campaign.json; InputError naming `what` (the flag or command reading it) if it is not one."""
    try:
        state = json.loads((cdir / CAMPAIGN_JSON).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{what} {cdir}: no {CAMPAIGN_JSON} there; not a campaign directory") from None
    if state.get("schema") != SCHEMA:
        raise InputError(f"{what} {cdir}: {CAMPAIGN_JSON} is not a {SCHEMA} file")
    return state


def new_state(plan: dict[str, Any], unit: str, simulate: dict[str, Any] | None) -> dict[str, Any]:
    return {
        "schema": SCHEMA,
        "complete": False,
        "started_utc": now_utc(),
        "finished_utc": None,
        "unit": unit,
        "method": plan["method"],
        "plan": plan,
        "simulate": simulate,
        "latitude_deg": None,
        "runs": [],
        "failed": [],
        "sessions": 1,
    }


def find_request(state: dict[str, Any], index: int, step: int, attempt: int, out: Path) -> FindRequest:
    """The find request (the `northfinder find` flags) for one find of the campaign."""
    plan, sim = state["plan"], state["simulate"]
    req = FindRequest(out=str(out), method=plan["method"], positions=plan.get("positions"),
                      dwell=plan.get("dwell_s"), unit=state.get("unit") or None,
                      no_report=not plan.get("report", True))
    if sim is None:
        req.config = plan["config"]
        return req
    req.simulate = True
    req.heading = float(plan["steps"][step]["reference_deg"])
    req.seed = int(sim["seed"]) + index + SEED_STRIDE * attempt
    req.grade = sim["grade"]
    req.time_scale = AUTO if sim["time_scale"] == AUTO else float(sim["time_scale"])
    for name, key in (("pitch", "pitch_deg"), ("roll", "roll_deg"), ("latitude", "latitude_deg")):
        if sim.get(key) is not None:
            setattr(req, name, float(sim[key]))
    req.sim_config = sim.get("sim_config") or None
    req.fault = tuple(sim.get("faults") or ())
    return req


def run_quietly(req: FindRequest, summary_path: Path) -> None:
    """One find with no view (the CLI passes its own runner that shows the progress and writes the
    summary to `summary_path`). Raises what the find raises."""
    KINDS["find"].measure(req)


def run_entry(run_dir: Path, cdir: Path, index: int, step: int, repeat: int, reference_deg: float):
    """campaign.json's record of a finished find, read from its result.json (the source of
    truth); None if the directory holds no complete result."""
    try:
        result = json.loads((run_dir / "result.json").read_text(encoding="utf-8"))
    except (FileNotFoundError, json.JSONDecodeError):
        return None
    return entry_from_result(result, run_dir, cdir, index, step, repeat, reference_deg)


def entry_from_result(
    result: dict[str, Any] | None, run_dir: Path, cdir: Path, index: int, step: int, repeat: int,
    reference_deg: float,
) -> dict[str, Any] | None:
    """campaign.json's record of a find from its result (live: result.json; replay: the find's
    replay); None for no complete result."""
    if not result or not result.get("complete"):
        return None
    methods = {m: v["heading_deg"] for m, v in result["methods"].items()}
    return {
        "index": index,
        "step": step,
        "repeat": repeat,
        "run_dir": str(run_dir.relative_to(cdir)),
        "reference_deg": float(reference_deg),
        "heading_deg": result["heading_deg"],
        "heading_std_deg": result["heading_std_deg"],
        "error_deg": float(deviation_deg(result["heading_deg"], reference_deg)),
        "methods": methods,
        "tilt_deg": result["tilt"]["tilt_deg"],
        "latitude_deg": result["latitude_deg"],
        "positions": result["positions_measured"],
        "duration_device_s": result["duration_device_s"],
    }


def update_statistics(state: dict[str, Any]) -> None:
    """Recompute the campaign's statistics from its runs (in place)."""
    runs = sorted(state["runs"], key=lambda r: r["index"])
    state["runs"] = runs
    if not runs:
        return
    state["latitude_deg"] = runs[0]["latitude_deg"]
    state["statistics"] = method_statistics(runs, state["method"])
    state["steps"] = step_statistics(runs, state["method"])
    state["mean_tilt_deg"] = sum(r["tilt_deg"] for r in runs) / len(runs)


def _set_aside(cdir: Path, run_dir: Path, state: dict[str, Any], index: int, reason: str) -> Path:
    """Move a stopped/failed find's directory aside (kept for replay and find --resume); the new
    path, which `reason` (the find's own line) then names instead of the old one."""
    attempt = 1 + sum(1 for f in state["failed"] if f["index"] == index)
    aside = run_dir.with_name(f"{run_dir.name}.failed-{attempt}")
    os.replace(run_dir, aside)
    reason = reason.replace(str(run_dir), str(aside))
    state["failed"].append(
        {"index": index, "run_dir": str(aside.relative_to(cdir)), "reason": reason, "utc": now_utc()}
    )
    return aside


def run_campaign(
    cdir: Path,
    state: dict[str, Any],
    *,
    runner: FindRunner = run_quietly,
    prompt: Callable[[int, float], None] | None = None,
    echo: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Measure every find of the plan that campaign.json does not list yet (in plan order);
    campaign.json after each. `prompt(step, reference_deg)` (a real bench) waits for the operator
    before the first find measured at each step. A stopped or failed find stops the campaign with
    one line saying how to resume."""
    done = {r["index"] for r in state["runs"]}
    attempts = {f["index"]: 0 for f in state["failed"]}
    for f in state["failed"]:
        attempts[f["index"]] += 1
    last_step = None
    total = len(planned(state["plan"]))
    for index, step, repeat in planned(state["plan"]):
        if index in done:
            continue
        reference = float(state["plan"]["steps"][step]["reference_deg"])
        run_dir = cdir / run_name(step, repeat)
        entry = run_entry(run_dir, cdir, index, step, repeat, reference) if run_dir.exists() else None
        if entry is None:
            if run_dir.exists():  # left incomplete by a session killed outright: kept aside
                why = "left incomplete by a killed session"
                _set_aside(cdir, run_dir, state, index, why)
                attempts[index] = attempts.get(index, 0) + 1
                write_state(cdir, state)
            try:
                if prompt is not None and step != last_step:
                    prompt(step, reference)
                last_step = step
                req = find_request(state, index, step, attempts.get(index, 0), run_dir)
                runner(req, run_dir / "summary.txt")
            except (NorthfinderError, KeyboardInterrupt) as exc:
                why = "stopped by Ctrl-C" if isinstance(exc, KeyboardInterrupt) else str(exc)
                if run_dir.exists():  # kept for replay; the find is measured again on --resume
                    why = str(_set_aside(cdir, run_dir, state, index, why)).join(why.split(str(run_dir)))
                raise _stopped(cdir, state, total, why, exc) from None
            entry = run_entry(run_dir, cdir, index, step, repeat, reference)
            if entry is None:
                err = InputError(f"{run_dir}: the find left no complete result")
                _set_aside(cdir, run_dir, state, index, str(err))
                raise _stopped(cdir, state, total, str(err), err)
        state["runs"].append(entry)
        update_statistics(state)
        write_state(cdir, state)
        echo(
            f"find {len(state['runs'])}/{total} ({run_dir.name}, reference {reference:.3f}°): "
            f"{state['method']} {entry['heading_deg']:.4f}° ± {entry['heading_std_deg']:.4f}°, "
            f"deviation {entry['error_deg'] * 60:+.3f}′"
        )
    state["complete"] = True
    state["finished_utc"] = now_utc()
    update_statistics(state)
    write_state(cdir, state)
    record_or_warn(cdir, unit=state.get("unit") or None)  # the campaign's row in the results history
    return state


def _stopped(cdir: Path, state: dict[str, Any], total: int, why: str, exc: BaseException) -> NorthfinderError:
    """The campaign's one line when a find (or the wait before one) stopped it."""
    write_state(cdir, state)
    k = len(state["runs"])
    err = RunAborted if isinstance(exc, KeyboardInterrupt | RunAborted) else NorthfinderError
    out = err(
        f"campaign {cdir}: {k} of {total} finds done; {why}; "
        f"continue it with northfinder campaign --resume {cdir}"
    )
    out.exit_code = getattr(exc, "exit_code", 130)
    return out


def is_campaign_dir(path: str | Path) -> bool:
    """A directory `northfinder campaign` made (its campaign.json)."""
    return (Path(path) / CAMPAIGN_JSON).is_file()


def replay_campaign(
    cdir: str | Path, method: str | None = None,
) -> tuple[dict[str, Any], list[tuple[dict[str, Any], Any]], dict[str, Any]]:
    """Replay every find a campaign lists (runkinds: the find's own replay) and recompute the
    campaign's statistics from the replayed results: (campaign.json as saved, [(its entry, the
    find's Replayed)], the state with the replayed numbers and statistics). The finds set aside
    (stopped, failed) are not in the statistics; replay them one by one. `method`: the finds'
    heading method (default: each find's own), also the one whose reported σ the statistics use."""
    cdir = Path(cdir)
    saved = json.loads((cdir / CAMPAIGN_JSON).read_text(encoding="utf-8"))
    if saved.get("schema") != SCHEMA:
        raise InputError(f"{cdir}: {CAMPAIGN_JSON} is not a {SCHEMA} file")
    replayed: list[tuple[dict[str, Any], Any]] = []
    runs = []
    for entry in saved["runs"]:
        out = KINDS["find"].replay(cdir / entry["run_dir"], method=method)
        replayed.append((entry, out))
        r = out.result
        if r is None:
            continue
        runs.append({**entry, "heading_deg": r["heading_deg"], "heading_std_deg": r["heading_std_deg"],
                     "error_deg": float(deviation_deg(r["heading_deg"], entry["reference_deg"])),
                     "methods": {m: v["heading_deg"] for m, v in r["methods"].items()},
                     "tilt_deg": r["tilt"]["tilt_deg"], "latitude_deg": r["latitude_deg"],
                     "positions": r["positions_measured"], "duration_device_s": r["duration_device_s"]})
    derived = ("statistics", "steps", "mean_tilt_deg")
    again = {**{k: v for k, v in saved.items() if k not in derived}, "runs": runs}
    if method is not None:
        again["method"] = method
    update_statistics(again)
    return saved, replayed, json.loads(json.dumps(again))


def replayed(cdir: str | Path, method: str | None = None) -> Replayed:
    """:func:`replay_campaign` as the campaign's replay in the run-kind registry: the campaign state
    with the replayed finds' records and statistics, and whether the campaign was complete."""
    saved, _, again = replay_campaign(cdir, method)
    return Replayed(again, bool(saved.get("complete")))
