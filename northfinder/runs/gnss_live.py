"""Live acquisition for `northfinder align --mode gnss`: the IMU and the GNSS read together.

What: open both ports with their raw logs in the run directory (imu.raw, gnss.nmea) and their
host receive stamps (imu.rx, gnss.rx), read `duration_s` of IMU device time (samples + lost
samples over the rate) with a rich progress bar, take every fix decoded by then, write the
window's sample range and fix count to events.jsonl, and compute the result through the same
function replay uses (northfinder.runs.gnss.result_from_run). Ctrl-C/SIGTERM: the data read so
far is kept and aligned if it is long enough; the CLI then exits 130 (143 for SIGTERM).

On the simulator (`VehicleSim`, firmware-sim `--scenario vehicle` as a subprocess) the IMU is not
put into configuration mode: the KVH sends nothing there and its sequence counter does not count
the pause, so the truth log's k0 would no longer map indices to device time. Its rate and format
are the ones firmware-sim is started with.
"""

from __future__ import annotations

import contextlib
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, ClassVar

from northfinder.config import GnssConfig, ImuConfig
from northfinder.devices import registry
from northfinder.errors import DeviceError
from northfinder.rundir import CONFIG, RunDir
from northfinder.runs import base
from northfinder.runs import gnss as gr
from northfinder.simulate import SimScenario, SimulatorProcess
from northfinder.stopflag import StopFlag

SIM_IMU_RATE_HZ = 250
SIM_DEFAULT_TIME_SCALE = 20.0
"""Device time runs 20× the wall clock: a 300 s drive in 15 s of reading (the simulator computes the
vehicle's truth at ~25× real time on one core of this 2-core host)."""
SIM_LEVER_ARM_M = (0.5, 1.5, 1.2)


@dataclass
class VehicleSim(SimScenario):
    """firmware-sim's vehicle scenario: the knobs passed on (simulate.SimScenario builds the command
    line and the record)."""

    scenario: ClassVar[str | None] = "vehicle"
    FLAGS: ClassVar[tuple[tuple[str, str, str], ...]] = (
        ("lever_arm_m", "--lever-arm", ""), ("imu_rate_hz", "--imu-rate", "int"), ("grade", "--grade", ""),
        ("seed", "--seed", "int"), ("time_scale", "--time-scale", "float"),
        ("latitude_deg", "--latitude", "float"),
        ("heading_deg", "--heading", "float"), ("truth_log", "--truth-log", "opt"),
        ("link_latency", "--link-latency", "opt"),
    )
    RECORDED: ClassVar[tuple[str, ...]] = ("lever_arm_m", "grade", "seed", "time_scale", "imu_rate_hz",
                                           "latitude_deg", "heading_deg", "faults", "link_latency")

    lever_arm_m: tuple[float, float, float] = SIM_LEVER_ARM_M
    grade: str = "kvh1760"
    seed: int = 1
    time_scale: float = SIM_DEFAULT_TIME_SCALE
    imu_rate_hz: int = SIM_IMU_RATE_HZ
    latitude_deg: float | None = None
    heading_deg: float | None = None
    faults: Sequence[str] = field(default_factory=tuple)
    truth_log: str | None = None
    link_latency: str | None = None
    """firmware-sim's `--link-latency` ("MS,JITTER_MS" or "imu=MS:J,gnss=MS:J", device ms): the
    links deliver late and jittery, as USB-serial adapters on a busy host do."""


class VehicleSimProcess(SimulatorProcess):
    """SimulatorProcess for the vehicle scenario: endpoints {"imu", "gnss", "gnss_start_utc"}."""

    required_endpoints = ("imu", "gnss")
    scenario_name = "vehicle"


def utc_seconds(iso: str) -> float:
    """'2026-11-22T12:00:00Z' → POSIX seconds."""
    return datetime.fromisoformat(iso.replace("Z", "+00:00")).astimezone(UTC).timestamp()


def _stamped(device: str, port: str, baudrate: int, raw: Path, stamps: Path) -> Any:
    from northfinder.transport import SerialTransport, StampedTransport

    return StampedTransport(
        SerialTransport(port, device=device, baudrate=baudrate, timeout_s=0.05, raw_log=raw), stamps
    )


def _progress_info(done_s: float, total_s: float, fix: Any, gnss_stats: Any, imu_stats: Any) -> str:
    """The progress bar's text: device time of the window, fixes, satellites, speed, stream counters."""
    speed = f"{fix.speed_m_s:5.1f} m/s" if fix is not None and fix.speed_m_s is not None else "  —  "
    sats = fix.num_sv if fix is not None else 0
    return (
        f"{done_s:6.1f}/{total_s:g} s  fixes {gnss_stats.fixes} ({sats} SV, {speed})  "
        f"NMEA bad {gnss_stats.bad_checksum}+{gnss_stats.truncated} no-fix {gnss_stats.no_fix}  "
        f"IMU lost {imu_stats.lost_samples} bad CRC {imu_stats.bad_crc}"
    )


@dataclass
class Window:
    """What one acquisition read: the IMU samples and fixes of the window and the run's events."""

    block: Any
    fixes: list[Any]
    start: dict[str, Any]
    end: dict[str, Any]
    stop: StopFlag


def _open_imu(rd: RunDir, imu: ImuConfig) -> contextlib.AbstractContextManager[Any]:
    """The IMU of `[imu]` with its raw log (imu.raw) and host receive stamps (imu.rx)."""
    return base.guard(
        "imu",
        imu.port,
        lambda: registry.open_device(
            "imu", imu, None,
            rate_hz=float(imu.rate_hz),
            rot_format=imu.rot_format,
            rot_units=imu.rot_units,
            timeout_s=5.0,
            transport=_stamped("imu", imu.port, imu.baudrate, rd.imu_raw_path, rd.file(gr.IMU_RX)),
        ),
    )


def _open_gnss(rd: RunDir, gnss: GnssConfig) -> contextlib.AbstractContextManager[Any]:
    """The receiver of `[gnss]` with its raw log (gnss.nmea) and host receive stamps (gnss.rx)."""
    return base.guard(
        "gnss",
        gnss.port,
        lambda: registry.open_device(
            "gnss", gnss, None,
            transport=_stamped("gnss", gnss.port, gnss.baudrate, rd.file(gr.GNSS_NMEA), rd.file(gr.GNSS_RX)),
        ),
    )


def _read_both(
    imu: Any, gnss: Any, duration_s: float, stop: StopFlag, blocks: list[Any], fixes: list[Any], view: Any
) -> None:
    """The IMU window in device time (base.read_imu_window); between reads, every fix the receiver
    has decoded, and the view's counters."""
    last_fix = None
    for done_s in base.read_imu_window(imu, duration_s, stop, blocks):
        pending = gnss.pending
        if pending:
            fixes.extend(gnss.read_fixes(pending, timeout_s=1.0))
            last_fix = fixes[-1]
        view.show(done_s, _progress_info(done_s, duration_s, last_fix, gnss.stats, imu.stats))


def _fixes_to_window_end(
    gnss: Any, last_index: int, rate_hz: float, gnss_start_utc: str, time_scale: float, fixes: list[Any]
) -> None:
    """The simulator's fixes up to the window's end are on their way (device time = NMEA UTC −
    gnss_start_utc): wait for them, bounded in host time by the time scale."""
    t_end = utc_seconds(gnss_start_utc) + (last_index + 1) / rate_hz + 0.5
    with contextlib.suppress(DeviceError):
        fixes.extend(gnss.fixes_until(t_end, timeout_s=2.0 + 1.0 / max(time_scale, 1e-3)))


def _end_window(
    rd: RunDir,
    stop: StopFlag,
    blocks: list[Any],
    fixes: list[Any],
    rate: float,
    start: dict[str, Any],
    gnss_start_utc: str | None,
    imu_stats: Any,
    gnss_stats: Any,
) -> Window:
    """The end event (the window's index range, fix count, counters, the UTC reference of device
    time) and the Window; no IMU sample read ends the run (RunAborted if a signal stopped it)."""
    complete = not stop
    if not blocks:
        rd.log_event(
            {"event": "end", "complete": False, "imu": {"samples": 0}, "gnss": {"fixes": len(fixes)}}
        )
        raise base.abort_or(stop, rd, "no IMU samples were read")
    block = base.concat_blocks(blocks, rate)
    utc_ref = (
        utc_seconds(gnss_start_utc) if gnss_start_utc else (math.floor(fixes[0].time_s) if fixes else 0.0)
    )
    end = {
        "event": "end",
        "complete": complete,
        "utc": base.now_utc(),
        "utc_ref_s": utc_ref,
        "imu": base.imu_end(block, imu_stats.as_dict()),
        "gnss": {"fixes": len(fixes), "stats": gnss_stats.as_dict()},
    }
    rd.log_event(end)
    return Window(block, fixes, start, end, stop)


def acquire(
    rd: RunDir,
    *,
    imu: ImuConfig,
    gnss: GnssConfig,
    duration_s: float,
    filter_settings: dict[str, Any],
    configure_imu: bool = False,
    simulate: dict[str, Any] | None = None,
    gnss_start_utc: str | None = None,
    time_scale: float = 1.0,
    progress: base.WindowProgress | None = None,
    config_extra: dict[str, Any] | None = None,
) -> Window:
    """Read the IMU of `[imu]` and the receiver of `[gnss]` (their models, ports, rates …) for
    `duration_s` device seconds; the raw logs, stamps and events are saved in the run directory. A
    signal ends the reading early (`Window.stop` says which)."""
    rd.write_json(CONFIG, {"kind": gr.KIND, "simulate": simulate, "argv": sys.argv, **(config_extra or {})})
    stop = StopFlag()
    blocks: list[Any] = []
    fixes: list[Any] = []
    base.prepare_to_stream(("imu", imu), ("gnss", gnss))
    with stop.installed(), contextlib.ExitStack() as stack:
        device = stack.enter_context(_open_imu(rd, imu))
        if configure_imu:
            device.configure_for_run(None)  # read the rate and gyro format back: the decoder must know them
        receiver = stack.enter_context(_open_gnss(rd, gnss))
        start = base.start_event(
            gr.KIND,
            duration_s,
            imu.port,
            device,
            gnss={"port": gnss.port, "model": receiver.model_name},
            filter=filter_settings,
            simulate=simulate,
            time_scale=time_scale,
            gnss_start_utc=gnss_start_utc,
            gnss_latency_s=gnss.latency_s,
        )
        rd.log_event(start)
        rate = device.rate_hz
        with base.window_view(progress, duration_s) as view:
            _read_both(device, receiver, duration_s, stop, blocks, fixes, view)
            if not stop and gnss_start_utc is not None and blocks:
                last = int(blocks[-1].sample_index[-1])
                _fixes_to_window_end(receiver, last, rate, gnss_start_utc, time_scale, fixes)
            pending = receiver.pending
            if pending:
                fixes.extend(receiver.read_fixes(pending, timeout_s=1.0))
            imu_stats, gnss_stats = device.stats, receiver.stats
    # ports closed: the raw logs and stamps are complete on disk
    return _end_window(rd, stop, blocks, fixes, rate, start, gnss_start_utc, imu_stats, gnss_stats)


def finish(rd: RunDir, w: Window, *, json_path: str | None = None, report: bool = True) -> dict[str, Any]:
    """Align on the window (the function replay uses), save result.json (+ --json) and report.png.
    A window cut short by a signal is aligned if it can be, then RunAborted (exit 130/143)."""
    return base.finish_window(
        rd,
        w.stop,
        lambda complete: gr.result_from_run(rd, w.block, w.fixes, w.start, w.end, complete),
        lambda result, hist: gr.save_result(rd, result, hist, json_path, report),
    )

