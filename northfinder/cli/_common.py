"""What the two `northfinder align` CLIs (--mode swaying, --mode gnss) share: argparse helpers, the
device-time progress bar handed to the runs as their view, the summary's rich rows and the end of a run.

A shared CLI module, not a subcommand: `cli/align_swaying.py`, `cli/align_gnss.py` (and replay,
through them) import it, so no subcommand module imports another.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import threading
from pathlib import Path
from typing import Any

from northfinder.align.limits import latitude_problem
from northfinder.errors import InputError

HEADING_RANGE_DEG = (-360.0, 360.0)
"""What `--heading` accepts: one turn either way. A value outside (400 for 40, a typo) is refused,
not wrapped silently."""


def heading_deg(text: str) -> float:
    """argparse type of `--heading DEG` (find, align): degrees from north, clockwise, within one
    turn; the simulator wraps it to 0…360."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of degrees") from None
    lo, hi = HEADING_RANGE_DEG
    if not (math.isfinite(value) and lo < value < hi):
        raise argparse.ArgumentTypeError(
            f"{text}: give a heading between {lo:g} and {hi:g} degrees (0…360 from north, clockwise)"
        )
    return value


def add_flag(parser: argparse.ArgumentParser, flag: str, **kwargs: Any) -> None:
    """Add a flag unless another align mode already did (`--heading`, `--latitude` are shared)."""
    if flag not in parser._option_string_actions:
        parser.add_argument(flag, **kwargs)


def add_db_flag(parser: argparse.ArgumentParser) -> None:
    """`--db`: the results history a command records into or reads (every command the same words)."""
    add_flag(
        parser,
        "--db",
        metavar="PATH|URL",
        help="results history: a SQLite file or postgresql://user@host/db "
        "(default $NORTHFINDER_HISTORY_DB, else the per-user history)",
    )


def apply_db_flag(args: argparse.Namespace) -> None:
    """Make `--db` the history every run of this command records into (the runs read
    $NORTHFINDER_HISTORY_DB; a campaign's finds inherit it)."""
    from northfinder.history import ENV_DB, is_url

    db = getattr(args, "db", None)
    if db:
        os.environ[ENV_DB] = db if is_url(db) else str(Path(db).resolve())


def history_place(run_dir: str) -> str:
    """One line: whether the history (--db, else the default) holds this run's row."""
    from northfinder import history

    db = history.default_db()
    key = history.run_id(Path(run_dir).resolve())
    try:
        with history.connect(db) as conn:
            found = conn.rows("SELECT run_id FROM runs WHERE run_id = ?", (key,))
    except history.HistoryError as exc:
        raise InputError(str(exc)) from None
    state = "holds this run" if found else f"does not hold this run (northfinder history --rebuild {run_dir})"
    return f"results history {history.label(db)} {state}"


def check_latitude(args: argparse.Namespace) -> None:
    """`--latitude` inside the align estimators' range (the same words in both modes and in a
    bench file's [site] latitude_deg: northfinder.align.limits)."""
    lat = getattr(args, "latitude", None)
    problem = latitude_problem(lat) if lat is not None else None
    if problem:
        raise InputError(f"--latitude {lat:g}: {problem}")


class DeviceTimeProgress:
    """rich progress bar in device time on stderr; `show(done_s, info)` with the mode's counters.
    The align runs take it as their `progress` hook (they never import the view)."""

    def __init__(self, duration_s: float, enabled: bool = True):
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        self.progress = Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            TextColumn("{task.fields[info]}"),
            TimeElapsedColumn(),
            console=Console(stderr=True),
            disable=not enabled,
        )
        self.plain = enabled and not self.progress.console.is_terminal
        """stderr is a file or a pipe: a plain line at each tenth of the window, no redrawn bar."""
        self.duration_s = duration_s
        self._tenths_shown = -1
        if self.plain:
            self.progress.disable = True
        self.task = self.progress.add_task("device time", total=duration_s, info="waiting for data")

    def show(self, done_s: float, info: str) -> None:
        if self.plain:
            tenth = int(10 * done_s / self.duration_s) if self.duration_s > 0 else 10
            if tenth > self._tenths_shown:
                self._tenths_shown = tenth
                print(f"device time {done_s:.0f} of {self.duration_s:g} s: {info}", file=sys.stderr,
                      flush=True)
            return
        self.progress.update(self.task, completed=done_s, info=info)

    def __enter__(self) -> DeviceTimeProgress:
        self.progress.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.progress.stop()


def summary_console(console: Any, min_width: int) -> Any:
    """The console to print on: a given one, else stdout (at least `min_width` wide when piped)."""
    from rich.console import Console

    if console is None:
        console = Console()
        if not console.is_terminal:
            console = Console(width=max(console.width, min_width))
    return console


def summary_head(title: str, result: dict[str, Any]) -> Any:
    """The summary's first table with its heading row."""
    from rich.table import Table

    head = Table(title=title, show_header=False, box=None)
    head.add_row(
        "heading",
        f"[bold]{result['heading_deg']:.4f}° ± {result['heading_std_deg']:.4f}°[/] (1σ, {result['method']})",
    )
    return head


def add_error_rows(head: Any, result: dict[str, Any], truth_text: str) -> None:
    """The truth row and the error in units of the reported σ."""
    ratio = abs(result["error_deg"]) / result["heading_std_deg"] if result["heading_std_deg"] else math.inf
    head.add_row("truth", truth_text)
    head.add_row("error", f"[bold]{result['error_deg']:+.4f}°[/] ({ratio:.2f} σ)")


def print_head(console: Any, head: Any, result: dict[str, Any]) -> None:
    """The incomplete marker (a run stopped early) and the head table."""
    if not result.get("complete", True):
        head.add_row("[red]INCOMPLETE[/]", "stopped before the end of the window")
    console.print(head)


def finish_and_print(
    args: argparse.Namespace,
    rd: Any,
    window: Any,
    finish: Any,
    print_summary: Any,
    t_wall: float,
    analysis: str,
) -> int:
    """The end of an align run in both modes: the run's `finish` (estimators, result, report),
    the results history, the summary, and the wall time split into acquisition and `analysis`."""
    import sys
    import time

    from northfinder.history import record_or_warn

    t_read = time.monotonic()
    result = finish(rd, window, json_path=args.json)
    record_or_warn(rd.path, unit=getattr(args, "unit", None))  # the results history (an index)
    print_summary(result, run_dir=rd.path)
    t_end = time.monotonic()
    print(
        f"wall time {t_end - t_wall:.1f} s: devices (and simulator) {t_read - t_wall:.1f} s, "
        f"{analysis} {t_end - t_read:.1f} s",
        file=sys.stderr,
    )
    return 0


def preload_matplotlib() -> None:
    """Import matplotlib (a second or two) in a thread while the devices or the simulator start, so
    the report does not wait for it. Not a daemon: a run that ends at once (a wrong port) lets the
    import finish before the interpreter shuts down — a daemon thread still inside it then crashed
    the process at exit ("Fatal Python error: PyThreadState_Get … finalizing", once in CI)."""
    threading.Thread(target=_import_matplotlib, name="preload-matplotlib").start()


def _import_matplotlib() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot  # noqa: F401
