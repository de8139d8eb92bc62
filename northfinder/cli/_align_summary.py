"""The align modes' printed summaries: `align --mode gnss|swaying` print them after a run and
`northfinder replay` after recomputing one — a shared CLI module, not a subcommand, so that no
subcommand module imports another."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from northfinder.cli import _common


def _f(v: Any, fmt: str, none: str = "—") -> str:
    return none if v is None else format(v, fmt)


def from_window_start(result: dict[str, Any], after_filter_start_s: float | None) -> float | None:
    """A time counted from the filter's start (`converged_after_s`) counted instead from the first
    IMU sample, as `time_below_1deg_s` is: both filters start at the same GNSS update
    (`filter_start_s`, the first after the levelling), so one shift serves both."""
    return None if after_filter_start_s is None else after_filter_start_s + result["filter_start_s"]


def start_text(result: dict[str, Any]) -> str:
    """Which heading start the filter used: a prior with its σ, or unknown (the first turn decides)."""
    psi0, std = result["initial_heading_deg"], result.get("initial_heading_std_deg")
    if std is None:
        text = f"heading unknown (filter started at {psi0:.2f}°, uniform prior; the first turn decides)"
        r = result.get("restart")
        if r:
            text += (f"; at {r['t_s']:.1f} s ({r['coarse_heading_deg']:.2f}° ± {r['coarse_std_deg']:.2f}°) "
                     f"started again from the still start at {r['initial_heading_deg']:.2f}° ± "
                     f"{r['prior_std_deg']:.2f}°")
        return text
    return f"prior {psi0:.2f}° ± {std:g}° (1σ), held while standing still"


def time_alignment_text(ta: dict[str, Any]) -> str:
    """The method; for `data` the correction to the host stamps with its 1σ; on the simulator each
    estimate against the truth log; when the data could not tell, why."""
    parts = [ta["method"]]
    data = ta.get("data") or {}
    if ta["method"] == "data":
        parts.append(f"offset {data['correction_s'] * 1e3:+.1f} ± {data['std_s'] * 1e3:.1f} ms (1σ) "
                     f"from the host stamps, {data['epochs']} epochs")
    elif "unavailable" in data:
        parts.append(f"(data: {data['unavailable']})")
    vs = [f"{name} {ta[key] * 1e3:+.1f} ms" for name, key in
          (("data", "data_minus_truth_s"), ("host stamps", "host_minus_truth_s")) if key in ta]
    text = " ".join(parts)
    return text + ("; against the truth log: " + ", ".join(vs) if vs else "")


def add_unknown_gap_row(head: Any, result: dict[str, Any]) -> None:
    """Where the window was cut at a gap of unknown length (runs.base.before_unknown_gap)."""
    cut = result.get("imu_unknown_gap")
    if cut:
        head.add_row("IMU cut", f"at {cut['at_s']:.1f} s into the window: {cut['why']}; the result uses "
                     f"the {cut['kept_s']:.1f} s before it ({cut['dropped_samples']} samples after it left "
                     "out). Keep the host from overrunning the IMU line (a lighter load, a lower rate).")


def print_gnss_summary(result: dict[str, Any], console: Any = None, run_dir: Path | None = None) -> None:
    """The rich summary: heading ± σ, convergence, lever arm, both filters, truth and errors, counters."""
    from rich.table import Table

    console = _common.summary_console(console, 132)
    head = _common.summary_head("northfinder align --mode gnss", result)
    head.add_row("start", start_text(result))
    noise = result.get("imu_noise") or {}
    if noise:
        src = noise["noise_source"]
        head.add_row("IMU noise", f"{src}: ARW {noise['gyro_arw_deg_sqrt_h']:g} °/√h, VRW "
                     f"{noise['accel_vrw_ug_sqrt_hz']:g} µg/√Hz"
                     + (" (conservative: IMU grade not known)" if src == "default" else ""))
    head.add_row(
        "converged after",
        f"{_f(from_window_start(result, result['converged_after_s']), '.1f')} s (1σ < 1° from then on; "
        f"from the first IMU sample, the filter started at {result['filter_start_s']:.1f} s)",
    )
    la, las = result["lever_arm_m"], result["lever_arm_std_m"]
    head.add_row(
        "lever arm",
        "(" + ", ".join(f"{v:+.3f}" for v in la) + ") m ± (" + ", ".join(f"{v:.3f}" for v in las) + ")",
    )
    head.add_row("pitch, roll", f"{result['pitch_deg']:+.3f}°, {result['roll_deg']:+.3f}°")
    head.add_row(
        "device time", f"{result['duration_device_s']:.1f} s, {result['gnss']['updates']} GNSS updates"
    )
    head.add_row("time alignment", time_alignment_text(result["time_alignment"]))
    add_unknown_gap_row(head, result)
    if "truth" in result:
        tr = result["truth"]
        _common.add_error_rows(
            head, result, f"heading {tr['heading_deg']:.4f}° (at the start {tr['heading_at_start_deg']:.4f}°)"
        )
        head.add_row(
            "position error",
            f"{_f(result.get('position_error_m'), '.2f')} m; lever arm off by "
            f"{_f(result.get('lever_arm_error_m'), '.3f')} m",
        )
    _common.print_head(console, head, result)
    t = Table(
        title="both filters on the same data (* = the result); times from the first IMU sample",
        caption="converged: 1σ < 1° to the end; <1°, <0.5°: the true error below it to the end",
    )
    for col in (
        "filter",
        "heading [deg]",
        "1σ [deg]",
        "converged [s]",
        "error [deg]",
        "<1° after [s]",
        "<0.5° after [s]",
    ):
        t.add_column(col, justify="right")
    for name, m in result["methods"].items():
        t.add_row(
            name + (" *" if name == result["method"] else ""),
            f"{m['heading_deg']:.4f}",
            f"{m['heading_std_deg']:.4f}",
            _f(from_window_start(result, m["converged_after_s"]), ".1f"),
            _f(m.get("error_deg"), "+.4f"),
            _f(m.get("time_below_1deg_s"), ".1f"),
            _f(m.get("time_below_0p5deg_s"), ".1f"),
        )
    console.print(t)
    s = result["gnss"]["stats"]
    i = result["imu"]["stats"]
    console.print(
        f"NMEA: {s['sentences']} sentences, {s['fixes']} fixes, bad checksum {s['bad_checksum']}, "
        f"truncated {s['truncated']}, no-fix {s['no_fix']}, malformed {s['malformed']}, "
        f"missed epochs {s['missed_epochs']}; IMU: {result['imu']['samples']} samples, lost "
        f"{result['imu']['lost_samples']}, bad CRC {i['bad_crc']}"
    )
    if run_dir is not None:
        console.print(f"run directory: {run_dir}")


def print_swaying_summary(result: dict[str, Any], console: Any = None, run_dir: Path | None = None) -> None:
    """The rich summary: heading ± σ, pitch, roll, truth and error, the coarse alignment for contrast."""
    from rich.table import Table

    console = _common.summary_console(console, 120)
    head = _common.summary_head("northfinder align --mode swaying", result)
    head.add_row(
        "pitch, roll",
        f"{result['pitch_deg']:+.3f}° ± {result['pitch_std_deg']:.4f}°, "
        f"{result['roll_deg']:+.3f}° ± {result['roll_std_deg']:.4f}° (at the end of the window)",
    )
    imu = result["imu"]
    head.add_row(
        "device time",
        f"{result['duration_device_s']:.1f} s, {imu['samples']} samples, lost "
        f"{imu['lost_samples']}, bad CRC {imu['stats']['bad_crc']}",
    )
    add_unknown_gap_row(head, result)
    if "truth" in result:
        tr = result["truth"]
        _common.add_error_rows(
            head,
            result,
            f"heading {tr['heading_deg']:.4f}°, pitch {tr['pitch_deg']:+.3f}°, roll "
            f"{tr['roll_deg']:+.3f}° at device time {tr['t_device_s']:.3f} s",
        )
    _common.print_head(console, head, result)
    t = Table(title="on the same samples (* = the result)")
    for col in ("method", "heading [deg]", "1σ [deg]", "error [deg]"):
        t.add_column(col, justify="right")
    for name, m in result["methods"].items():
        err = m.get("error_deg")
        t.add_row(
            name + (" *" if name == result["method"] else ""),
            f"{m['heading_deg']:.4f}",
            "—" if m["heading_std_deg"] is None else f"{m['heading_std_deg']:.4f}",
            "—" if err is None else f"{err:+.4f}",
        )
    console.print(t)
    cov = result.get("sigma_covers")
    if cov:
        console.print(f"1σ covers: {'; '.join(cov['covers'])}. Not in it: {'; '.join(cov['omits'])}.")
    if run_dir is not None:
        console.print(f"run directory: {run_dir}")
