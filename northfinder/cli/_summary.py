"""The find's views: the live progress (find, campaign) and the result's summary as rich tables
(find, find --resume, replay, campaign's summary.txt).

A shared CLI module, not a subcommand: `cli/find.py` and `cli/replay.py` both import it, so no
subcommand module imports another.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, TextColumn, TimeElapsedColumn
from rich.progress import Progress as BarProgress
from rich.table import Table

from northfinder.cli._tables import print_fitted
from northfinder.constants import wrap_deg_180
from northfinder.sequencer import Progress


def print_summary(result: dict[str, Any], console: Any = None, run_dir: Path | None = None) -> None:
    """The rich summary table: heading ± σ, tilt, every method, positions, truth and error."""
    if console is None:
        console = Console()
        if not console.is_terminal:  # piped or captured: do not squeeze the tables into 80 columns
            console = Console(width=max(console.width, 132))
    console.print(_head_table(result))
    console.print(_methods_table(result))
    print_fitted(console, "positions", _POSITION_COLUMNS, position_rows(result))
    _print_faults(result.get("faults"), console)
    if run_dir is not None:
        console.print(f"run directory: {run_dir}")


def print_positions(positions: list[dict[str, Any]], console: Any = None) -> None:
    """The positions table alone (a partial run with too few positions for a heading)."""
    if console is None:
        console = Console()
        if not console.is_terminal:
            console = Console(width=max(console.width, 132))
    print_fitted(console, "positions", _POSITION_COLUMNS, position_rows({"positions": positions}))


def _head_table(result: dict[str, Any]) -> Any:
    """Heading ± σ, tilt, latitude, device time; truth and error of a simulated run."""
    t = result["tilt"]
    head = Table(title="northfinder result", show_header=False, box=None)
    head.add_row(
        "heading",
        f"[bold]{result['heading_deg']:.4f}° ± {result['heading_std_deg']:.4f}°[/] (1σ, {result['method']})",
    )
    head.add_row(
        "tilt",
        f"{t['tilt_deg']:.4f}° toward {t['tilt_azimuth_deg']:.2f}°  "
        f"(pitch {t['pitch_deg']:+.4f}°, roll {t['roll_deg']:+.4f}°)",
    )
    head.add_row("latitude", f"{result['latitude_deg']:.4f}°")
    n_pos = result["positions_measured"]
    head.add_row("device time", f"{result['duration_device_s']:.1f} s of dwell over {n_pos} positions")
    for label, text in _plan_rows(result):
        head.add_row(label, text)
    if "truth" in result:
        tr = result["truth"]
        head.add_row(
            "truth",
            f"heading {tr['heading_deg']:.4f}°, pitch {tr['pitch_deg']:+.4f}°, roll {tr['roll_deg']:+.4f}°",
        )
        ratio = (
            abs(result["error_deg"]) / result["heading_std_deg"] if result["heading_std_deg"] else math.inf
        )
        head.add_row("error", f"[bold]{result['error_deg']:+.4f}°[/] ({ratio:.2f} σ)")
    if not result.get("complete", True):
        head.add_row(
            "[red]INCOMPLETE[/]",
            f"{result['positions_measured']} of {result['positions_planned']} positions measured",
        )
    return head


def _plan_rows(result: dict[str, Any]) -> list[tuple[str, str]]:
    """What the heading used (the dwells, or every sample) and what the plan predicted."""
    rows = []
    motion, dwell = result.get("motion_fit"), result.get("dwell_fit")
    if motion is not None and motion.get("available"):
        n = motion["samples"]
        kind = result.get("plan", "positions+motion")
        how = " (rests reached the long way round, whole turns both ways)" if kind == "sweep" else ""
        last = "the rest after the return" if n.get("through_return") else "the last"
        sessions = motion.get("sessions")
        where = (f" in {len(sessions)} sessions (a gyro bias each: their sample counters do not join)"
                 if sessions else "")
        rows.append(("plan", f"{kind}{how}: every gyro sample, {n['used_device_s']:.1f} s from the "
                     f"first dwell to {last}{where} (dwells alone ±{dwell['heading_std_deg']:.4f}°)"))
    elif motion is not None:
        rows.append(("plan", "positions (dwells only): the motion samples could not be used — "
                     f"{motion['reason']}"))
    else:
        rows.append(("plan", f"{result.get('plan', 'positions')}: the dwell means"))
    pred = result.get("plan_prediction")
    if pred:
        goal = (f"target {pred['target_std_deg']:g}°" if pred.get("target_std_deg") is not None
                else f"budget {pred['time_budget_s']:g} s")
        rows.append(("predicted", f"± {pred['predicted_std_deg']:.4f}° in "
                     f"{pred['predicted_elapsed_s']:.0f} s ({goal}, {pred['grade']}, "
                     f"{pred['positions']} × {pred['dwell_s']:g} s)"))
    return rows


def _methods_table(result: dict[str, Any]) -> Any:
    """Every method's heading (and its error against the truth of a simulated run)."""
    methods = Table(title="every method (* = the result)")
    methods.add_column("method")
    methods.add_column(escape("heading [deg]"), justify="right")
    if "truth" in result:
        methods.add_column(escape("error [deg]"), justify="right")
    for name, m in result["methods"].items():
        h = m.get("heading_deg")
        row = [name + (" *" if name == result["method"] else ""), "—" if h is None else f"{h:.4f}"]
        if "truth" in result:
            err = "—" if h is None else f"{float(wrap_deg_180(h - result['truth']['heading_deg'])):+.4f}"
            row.append(err)
        methods.add_row(*row)
    return methods


_POSITION_COLUMNS = ("#", "α [deg]", "gyro x [°/h]", "gyro y [°/h]", "gyro z [°/h]", "accel x [mg]",
                     "accel y [mg]", "accel z [mg]", "samples", "lost", "accel n", "accel lost")


def position_rows(result: dict[str, Any]) -> list[list[str]]:
    """One row per position: table angle, gyro and accelerometer means, sample counts (as text)."""
    rows = []
    for i, p in enumerate(result["positions"], 1):
        g, a = p["gyro_dph"], p["accel_g"]
        rows.append([
            str(i),
            f"{p['table_angle_deg']:.3f}",
            *("—" if v is None or v != v else f"{v:+.4f}" for v in g),  # an axis the unit lacks
            *("—" if v is None else f"{v * 1e3:+.3f}" for v in a),
            str(p["samples"]),
            str(p["lost_samples"]),
            str(p["accel_samples"]),
            str(p["accel_lost_samples"]),
        ])
    return rows


def _invalid_lines(imu: dict[str, Any]) -> list[str]:
    """The IMU samples flagged not valid per axis (status bits), if the unit flagged any."""
    counts = imu.get("invalid_samples") or {}
    if not any(counts.values()):
        return []
    each = ", ".join(f"{k} {v}" for k, v in counts.items())
    dwells = ", ".join(f"{k} {v}" for k, v in (imu.get("invalid_in_dwells") or {}).items())
    return [f"IMU samples flagged not valid (left out): {each} in the stream ({dwells} inside kept dwells)"]


def _print_faults(faults: dict[str, Any] | None, console: Any) -> None:
    """What went wrong and what was done: lost samples, re-measured positions, stage errors, EMCY."""
    if not faults:
        return

    imu, acc = faults["imu"], faults["accel"]
    lines = [
        f"IMU: {imu['bad_crc']} bad CRC, {imu['resyncs']} resyncs, {imu['sequence_gaps']} gaps, "
        f"{imu['lost_samples']} samples lost in the stream ({imu['lost_in_dwells']} inside kept dwells), "
        f"{imu['reconnects']} reconnects",
        *_invalid_lines(imu),
        f"accelerometer: {acc['lost_samples']} samples lost ({acc['lost_in_dwells']} inside kept dwells), "
        f"{acc['emcy']} EMCY, heartbeats {acc['heartbeats']}",
    ]
    if acc.get("kernel_drops"):
        lines.append(f"  {acc['kernel_drops']} CAN frames dropped by the kernel: the socket's receive buffer "
                     "was full (the reader fell behind the bus)")
    for m in acc["emergencies"]:
        lines.append(f"  EMCY 0x{m['code']:04X} register 0x{m['register']:02X}: {m['meaning']}")
    if acc["heartbeat_lost_positions"]:
        pos = ", ".join(str(k + 1) for k in acc["heartbeat_lost_positions"])
        lines.append(f"  no heartbeat from the node during position(s) {pos}: node watch lost")
    for r in faults["remeasured"]:
        lines.append(
            f"position {r['index'] + 1} measured again (attempt {r['attempt']} rejected): {r['reason']}"
        )
    for e in faults["stage_errors"]:
        lines.append(
            f"stage error on the move to {e['target_deg']:g}° (attempt {e['attempt']}): {e['error']}"
        )
    if faults.get("sessions", 1) > 1:
        lines.append(f"measured in {faults['sessions']} sessions (resumed)")
    console.print("[bold]faults[/]")
    for line in lines:
        console.print(escape(line))


NARROW_COLUMNS = 120
"""A terminal narrower than this gets the compact live progress (ProgressView.narrow)."""


class ProgressView:
    """rich live progress: position k of n, dwell in device time, live gyro mean and σ."""

    def __init__(self, n: int, dwell_s: float, enabled: bool = True):
        self.console = Console(stderr=True)
        self.enabled = enabled
        self.plain = enabled and not self.console.is_terminal
        """stderr is a file or a pipe: one plain line per event instead of a redrawn bar."""
        self._last_dwell: Progress | None = None
        self.narrow = self.console.width < NARROW_COLUMNS
        """Below NARROW_COLUMNS: a short bar and the dwell's numbers without words, so that no line is cut."""
        self.progress = BarProgress(
            TextColumn("{task.description}"),
            BarColumn(bar_width=8 if self.narrow else 40),
            TextColumn("{task.fields[info]}"),
            TimeElapsedColumn(),
            console=self.console,
            transient=False,
            disable=not enabled or self.plain,
        )
        self.pos_task = self.progress.add_task("positions", total=n, info="referencing the stage")
        self.dwell_task = self.progress.add_task("dwell", total=dwell_s, info="")

    def __call__(self, p: Progress) -> None:
        if self.plain:
            self._plain_line(p)
            return
        if p.phase in ("move", "settle", "return", "reference"):
            what = {
                "move": f"moving to {p.target_deg:.1f}°",
                "settle": "settling (gyro-z ringing)",
                "return": "returning to the start",
                "reference": "referencing the stage",
            }[p.phase]
            self.progress.update(
                self.pos_task, info=f"position {max(p.position, 1)} of {p.positions}: {what}"
            )
            if p.phase == "move":
                self.progress.update(self.dwell_task, completed=0.0, info="")
        elif p.phase == "dwell":
            m, s = p.gyro_mean_dph, p.gyro_std_of_mean_dph
            self.progress.update(
                self.pos_task, info=f"position {p.position} of {p.positions} at {p.target_deg:.1f}°"
            )
            if self.narrow:
                info = (f"{p.dwell_done_s:4.1f}/{p.dwell_s:g} s x {m[0]:+.2f} y {m[1]:+.2f} "
                        f"z {m[2]:+.2f} °/h σ {s[1]:.3f}")
            else:
                info = (f"{p.dwell_done_s:5.1f}/{p.dwell_s:g} s  gyro x {m[0]:+8.3f} y {m[1]:+8.3f} "
                        f"z {m[2]:+8.3f} °/h  σ(mean) {s[1]:.3f} °/h")
            self.progress.update(self.dwell_task, completed=p.dwell_done_s, info=info)
        elif p.phase == "measured":
            self.progress.update(self.pos_task, completed=p.position)

    def _plain_line(self, p: Progress) -> None:
        """One line per event (a move, a settle, a measured position, the return), none per update."""
        import sys

        if p.phase == "dwell":
            self._last_dwell = p
            return
        where = f"position {max(p.position, 1)} of {p.positions}"
        line = {
            "reference": "referencing the stage",
            "move": f"{where}: moving to {p.target_deg:.1f}°",
            "settle": f"{where}: settling",
            "return": "returning to the start",
        }.get(p.phase)
        if p.phase == "measured":
            d = self._last_dwell
            line = f"{where}: measured"
            if d is not None and d.position == p.position:
                m, s = d.gyro_mean_dph, d.gyro_std_of_mean_dph
                line += (f" at {d.target_deg:.1f}°, {d.dwell_done_s:.1f} s: gyro x {m[0]:+.3f} y {m[1]:+.3f} "
                         f"z {m[2]:+.3f} °/h, σ(mean) {s[1]:.3f} °/h")
        if line:
            print(line, file=sys.stderr, flush=True)

    def __enter__(self) -> ProgressView:
        self.progress.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.progress.stop()
