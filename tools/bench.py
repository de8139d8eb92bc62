#!/usr/bin/env python3
"""The product's measured speed, one table: figures, not pass/fail (issue 7).

Rows:

* **IMU decoder** — :class:`northfinder.codecs.kvh.KvhDecoder` on a stream of valid frames (fixed
  seed), pinned to one core: frames per second of wall and of CPU time, and the multiple of the
  1 kHz real-time rate (whole buffer = replay; 4096-byte chunks = what the driver's reader sees).
* **CAN path** — cantools decode + TPDO pairing (:class:`AccelFrameDecoder`), frames/s against
  the 200 frames/s of 100 Hz pairs; and slcan clients receiving TPDO lines from a pty: python-can's
  own (one byte per pyserial call, python-can issue #2027) and the one northfinder opens,
  :class:`northfinder.transport.ChunkedSlcanBus` (every waiting byte at once): the accelerometer
  link's ceiling, which limits the time-scaled runs below.
* **Driver CPU at 1 kHz real time** — ``python -m firmware_sim --time-scale 1`` as a subprocess,
  :class:`northfinder.drivers.imu.Imu` reading ~10 s: this process's CPU (``time.process_time``,
  every thread) and the simulator's (``/proc/<pid>/stat``), as % of one core; then the same with the
  CAN accelerometer at 100 Hz over slcan beside it (both streams of a find).
* **Monte Carlo** — ``montecarlo.simulate`` + ``heading.solve_batch`` for an 8 × 60 s plan,
  trials per second (simulate + solve, and solve only).
* **find end to end** — ``northfinder find --simulate --positions 8 --dwell 60`` at each time
  scale, largest first, until one loses nothing (IMU and accelerometer ``lost_samples`` summed
  over the positions of the result JSON); its wall time and the CPU of find and simulator.
  ``--profile`` then runs that find once more under cProfile and prints where its main thread
  spends the time.

The host (CPU model, cores, load average before and after) is printed first: on a shared
machine the figures mean little without it.

    python3 tools/bench.py                      # everything (several minutes: the find runs)
    python3 tools/bench.py --skip-find          # the quick rows only
    python3 tools/bench.py --scales 50,20 --profile
    python3 tools/bench.py --sample 20          # per-thread CPU and stacks of one find
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import platform
import pstats
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # run from a checkout without installing

from northfinder.codecs import kvh  # noqa: E402
from northfinder.codecs.canopen import AccelFrameDecoder, CanCodec  # noqa: E402
from northfinder.drivers.imu import Imu  # noqa: E402
from northfinder.estimators import montecarlo as mc  # noqa: E402
from northfinder.estimators.heading import solve_batch  # noqa: E402
from northfinder.runs.find import pace_note  # noqa: E402
from northfinder.runs.find_pace import paced_scales, time_scale_arg  # noqa: E402
from northfinder.transport import ChunkedSlcanBus  # noqa: E402

REAL_TIME_HZ = 1000.0
ENV = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))


@dataclass
class Row:
    what: str
    figure: str
    note: str = ""


# --------------------------------------------------------------------------------------------
# host


def host_lines() -> list[str]:
    model = "unknown"
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return [
        f"host      {platform.node()}  {platform.system()} {platform.release()}",
        f"cpu       {model}, {os.cpu_count()} cores ({affinity} usable by this process)",
        f"load avg  {load} (1, 5, 15 min) at start",
        f"python    {platform.python_version()}, numpy {np.__version__}",
    ]


def proc_cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux /proc/<pid>/stat, fields 14 and 15)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def children_of(pid: int) -> list[int]:
    out: list[int] = []
    with contextlib.suppress(OSError):
        for task in Path(f"/proc/{pid}/task").iterdir():
            with contextlib.suppress(OSError):
                out += [int(c) for c in (task / "children").read_text().split()]
    return out


@contextlib.contextmanager
def one_core():
    """Pin this process to one CPU for the block (the issue asks for figures on one core)."""
    if not hasattr(os, "sched_setaffinity"):
        yield None
        return
    before = os.sched_getaffinity(0)
    cpu = min(before)
    os.sched_setaffinity(0, {cpu})
    try:
        yield cpu
    finally:
        os.sched_setaffinity(0, before)


def timed(fn, repeats: int = 3) -> tuple[float, float]:
    """Best wall and best CPU seconds of `fn` over `repeats` runs."""
    wall, cpu = float("inf"), float("inf")
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall = min(wall, time.perf_counter() - w0)
        cpu = min(cpu, time.process_time() - c0)
    return wall, cpu


# --------------------------------------------------------------------------------------------
# rows


def bench_decoder(n: int, chunk_bytes: int) -> list[Row]:
    rng = np.random.default_rng(0)
    stream = kvh.encode_frames(rng.normal(scale=1e-5, size=(n, 3)), rng.normal(size=(n, 3)),
                               np.full(n, 0x77), np.arange(n), np.full(n, 25))

    def whole():
        assert len(kvh.KvhDecoder().feed(stream)) == n

    def chunked():
        dec = kvh.KvhDecoder()
        got = sum(len(dec.feed(stream[i:i + chunk_bytes])) for i in range(0, len(stream), chunk_bytes))
        assert got == n

    rows = []
    with one_core() as cpu:
        for label, fn in (("whole buffer (replay)", whole), (f"{chunk_bytes}-byte chunks (live)", chunked)):
            wall, cpu_s = timed(fn)
            rows.append(Row(f"IMU decoder, {label}",
                            f"{n / wall:,.0f} frames/s = {n / wall / REAL_TIME_HZ:,.0f}× real time",
                            f"CPU: {n / cpu_s:,.0f} frames/s = {n / cpu_s / REAL_TIME_HZ:,.0f}×; {n} frames, "
                            f"core {cpu}"))
    return rows


def bench_can(n_pairs: int = 5000) -> Row:
    codec = CanCodec()
    frames = []
    for c in range(n_pairs):
        frames.append(codec.encode("TPDO1", {"accel_x": c, "accel_y": -c}))
        frames.append(codec.encode("TPDO2", {"accel_z": 10**6, "temperature": 2500, "counter": c % 256,
                                             "status": 7}))

    def run():
        dec = AccelFrameDecoder(codec)
        for can_id, data in frames:
            dec.feed(can_id, data)
        assert len(dec.drain()) == n_pairs

    with one_core():
        wall, cpu_s = timed(run)
    k = len(frames)
    return Row("CAN decode + pairing (cantools)",
               f"{k / wall:,.0f} frames/s = {k / wall / 200:,.0f}× real time",
               f"real time = 200 frames/s (100 Hz pairs); CPU: {k / cpu_s:,.0f} frames/s")


def bench_slcan_client(bus_class: type | None = None, n_frames: int = 20_000) -> Row:
    """An slcan client receiving TPDO lines from a pty as fast as it can: the ceiling of the
    accelerometer link. `bus_class` None is python-can's stock client (one byte per pyserial call,
    python-can issue #2027); northfinder opens :class:`northfinder.transport.ChunkedSlcanBus`
    (tools/slcan_speed.py compares the two in more detail)."""
    from can.interfaces.slcan import slcanBus
    from slcan_speed import receive  # tools/ is sys.path[0] when run as a script

    bus_class = bus_class or slcanBus
    line = b"t1908E803000030F8FFFF\r"
    got, wall, cpu, _ = receive(bus_class, line * n_frames, n_frames, count_reads=False)
    label = "python-can slcan client" if bus_class is slcanBus else bus_class.__name__
    return Row(f"{label}, receive",
               f"{got / wall:,.0f} frames/s = {got / wall / 200:,.0f}× real time",
               f"CPU: {got / cpu:,.0f} frames/s; {len(line)}-byte TPDO lines from a pty; the sim needs "
               f"200 frames/s × time scale")


def start_sim(time_scale: float, seed: int = 1) -> tuple[subprocess.Popen, dict]:
    proc = subprocess.Popen([sys.executable, "-m", "firmware_sim", "--time-scale", repr(time_scale),
                             "--seed", str(seed)], cwd=ROOT, env=ENV, stdout=subprocess.PIPE)
    line = proc.stdout.readline()
    if not line:
        proc.kill()
        raise RuntimeError("firmware_sim printed no endpoints")
    return proc, json.loads(line)


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def bench_driver_cpu(seconds: float, time_scale: float = 1.0) -> Row:
    """Imu reading `seconds` of wall at `time_scale` × 1 kHz: CPU of this process and the sim."""
    proc, endpoints = start_sim(time_scale)
    try:
        with Imu(endpoints["imu"], timeout_s=5.0) as imu:
            imu.read(200)  # the stream is flowing; start counting from here
            s0 = imu.stats
            c0_self, c0_sim, t0 = time.process_time(), proc_cpu_s(proc.pid), time.monotonic()
            n = int(round(seconds * REAL_TIME_HZ * time_scale))
            got = 0
            while got < n:
                got += len(imu.read(min(int(250 * time_scale), n - got)))
            wall = time.monotonic() - t0
            c_self, c_sim = time.process_time() - c0_self, proc_cpu_s(proc.pid) - c0_sim
            s1 = imu.stats
    finally:
        stop(proc)
    lost = s1.lost_samples - s0.lost_samples
    if time_scale == 1.0:
        what = "driver CPU, 1 kHz in real time"
    else:
        what = f"IMU driver alone at {time_scale:g}× (no CAN)"
    # lost samples come from the 7-bit sequence, so a gap ≥ 128 counts short: the achieved rate
    # (samples per wall second) is the other witness — below the scale means the driver lost data
    return Row(what,
               f"{100 * c_self / wall:.1f} % of one core (reader + this script)",
               f"firmware-sim {100 * c_sim / wall:.1f} % (all its devices); {got} samples in "
               f"{wall:.2f} s wall = {got / wall / REAL_TIME_HZ:.1f}× real time; lost ≥ {lost}, "
               f"{s1.bad_crc - s0.bad_crc} bad CRC, {s1.resyncs - s0.resyncs} resyncs")


def bench_driver_cpu_with_can(seconds: float, accel_rate_hz: float = 100.0) -> Row:
    """The bench's two streams at real time, as a find reads them: the KVH IMU at 1 kHz and the
    CAN accelerometer at `accel_rate_hz` over slcan (northfinder's ChunkedSlcanBus on firmware-sim's
    adapter pty), both read by this thread: CPU of this process (every thread) and the sim's."""
    from northfinder.drivers.accelerometer import Accelerometer

    proc, endpoints = start_sim(1.0)
    can = endpoints["can"]
    try:
        with Imu(endpoints["imu"], timeout_s=5.0) as imu, \
                Accelerometer(can["interface"], can["channel"], bitrate=can.get("bitrate", 500000),
                              node_id=can.get("node_id", 0x10),
                              bus_options={"sleep_after_open": 0.05}) as acc:
            acc.wait_heartbeat()
            acc.configure(rate_hz=accel_rate_hz)
            acc.start_node()
            acc.read(int(accel_rate_hz // 5))
            imu.read(200)
            imu.discard_pending()
            acc.discard_pending()
            c0_self, c0_sim, t0 = time.process_time(), proc_cpu_s(proc.pid), time.monotonic()
            got_imu = got_acc = 0
            while time.monotonic() - t0 < seconds:
                got_imu += len(imu.read(250))
                got_acc += len(acc.read(max(1, int(accel_rate_hz // 4))))
            wall = time.monotonic() - t0
            c_self, c_sim = time.process_time() - c0_self, proc_cpu_s(proc.pid) - c0_sim
            lost = acc.stats.lost_samples
    finally:
        stop(proc)
    return Row(f"driver CPU, IMU 1 kHz + CAN {accel_rate_hz:g} Hz in real time",
               f"{100 * c_self / wall:.1f} % of one core (readers + this script)",
               f"firmware-sim {100 * c_sim / wall:.1f} %; {got_imu} IMU and {got_acc} accelerometer samples "
               f"in {wall:.1f} s; accelerometer lost {lost}")


def bench_montecarlo(trials: int) -> list[Row]:
    rng = np.random.default_rng(1)
    plan = mc.Plan(mc.equally_spaced_deg(8), dwell_s=60.0)
    gyro, accel = mc.GyroNoise(arw_deg_rt_h=0.01, bias_sigma_dph=0.5), mc.AccelNoise(noise_ug_rt_hz=20.0)
    full, solve = float("inf"), float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        b = mc.simulate(rng, trials, plan, 30.0, 2.0, 3.0, 40.0, gyro, accel, three_axis=True)
        t1 = time.perf_counter()
        solve_batch(b.table_angle_deg, b.gyro_dph, b.accel_g, 40.0, gyro_std_dph=b.gyro_std_dph,
                    accel_std_g=b.accel_std_g)
        t2 = time.perf_counter()
        full, solve = min(full, t2 - t0), min(solve, t2 - t1)
    return [Row("Monte Carlo, simulate + solve", f"{trials / full:,.0f} trials/s",
                f"8 positions × 60 s, 3-axis, {trials} trials per batch, best of 3"),
            Row("Monte Carlo, solve_batch only", f"{trials / solve:,.0f} trials/s", "")]


@dataclass
class FindRun:
    time_scale: float | str
    wall_s: float
    code: int | None
    imu_lost: int | None = None
    accel_lost: int | None = None
    device_s: float | None = None
    cpu_find_s: float | None = None
    cpu_sim_s: float | None = None
    error: str = ""
    gaps_s: list[float] | None = None
    """Device seconds from each dwell's last IMU sample to the next dwell's first (events.jsonl)."""
    before_move_s: list[float] | None = None
    """The position events' before_move_s: the host's share of each gap."""
    to_settled_s: list[float] | None = None
    """Dwell end → the next settle's last sample (its `end_index`), before the 1 s dwell grid rounds
    it up into the gap."""
    scales: list[float] | None = None
    """--time-scale auto: the scales the pace set, in order."""
    behind: str | None = None
    """The run's own line when this host did not keep up with its time scale (runs.find.pace_note:
    samples lost, or device time running on between a dwell and the next move), else None."""

    def gaps_note(self) -> str:
        if not self.gaps_s:
            return "no gaps (fewer than 2 positions)"
        g, lag = np.asarray(self.gaps_s), np.asarray(self.before_move_s or [np.nan])
        out = (f"gap between dwells median {np.median(g):.1f} s device ({g.min():.0f}–{g.max():.0f}: "
               f"{', '.join(f'{x:.0f}' for x in g)}), before_move_s median {np.nanmedian(lag):.1f}")
        if self.to_settled_s:
            out += f", settled {', '.join(f'{x:.2f}' for x in self.to_settled_s)} s after the dwell before"
        return out + (f"; scales {' → '.join(f'{k:g}' for k in self.scales)}" if self.scales else "")

    @property
    def lossless(self) -> bool:
        return self.code == 0 and self.imu_lost == 0 and self.accel_lost == 0

    def says(self) -> str:
        """What else the run said: its error, and its own line when the host fell behind."""
        said = f"; the run says: {self.behind}" if self.behind else ""
        return (f"; {self.error}" if self.error else "") + said

    @property
    def kept_up(self) -> bool:
        """Lossless, and the run did not say the host fell behind."""
        return self.lossless and self.behind is None


def find_cmd(time_scale: float | str, out: Path, seed: int) -> list[str]:
    return ["-m", "northfinder", "find", "--simulate", "--positions", "8", "--dwell", "60",
            "--time-scale", _scale_text(time_scale), "--seed", str(seed), "--no-report",
            "--json", str(out / "result.json"), "--out", str(out / "run")]


def _scale_text(time_scale: float | str) -> str:
    return time_scale if isinstance(time_scale, str) else f"{time_scale:g}"


def _read_gaps(run: FindRun, events_path: Path) -> None:
    """The run's gaps between dwells, the host's share of them and an auto run's scales."""
    if not events_path.exists():
        return
    events = [json.loads(ln) for ln in events_path.read_text().splitlines() if ln.strip()]
    pos = [e for e in events if e.get("event") == "position"]
    start = next((e for e in events if e.get("event") == "start"), {})
    rate = float(start.get("imu", {}).get("rate_hz", 1000))
    run.gaps_s = [(b["imu"]["first_index"] - a["imu"]["last_index"]) / rate
                  for a, b in zip(pos, pos[1:], strict=False)]
    run.before_move_s = [float(p["before_move_s"]) for p in pos if p.get("before_move_s") is not None]
    run.to_settled_s = [(b["settle"]["end_index"] - a["imu"]["last_index"]) / rate
                        for a, b in zip(pos, pos[1:], strict=False) if "end_index" in b["settle"]]
    run.scales = paced_scales(events) or None
    run.behind = pace_note(events)


def run_find(time_scale: float | str, timeout_s: float, seed: int,
             prefix: list[str] | None = None) -> FindRun:
    """One `northfinder find --simulate` as a user runs it; CPU of it and of its simulator."""
    out = Path(tempfile.mkdtemp(prefix="nf-bench-"))
    argv = [sys.executable, *(prefix or []), *find_cmd(time_scale, out, seed)]
    t0 = time.monotonic()
    proc = subprocess.Popen(argv, cwd=out, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    sim_cpu: dict[int, float] = {}
    stderr = bytearray()
    reader = threading.Thread(target=lambda: stderr.extend(proc.stderr.read()), daemon=True)
    reader.start()
    find_cpu = 0.0
    try:
        while proc.poll() is None:
            if time.monotonic() - t0 > timeout_s:
                proc.send_signal(signal.SIGINT)  # find stops the stage and saves what it has
                try:
                    proc.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    proc.kill()
                break
            with contextlib.suppress(OSError):
                find_cpu = proc_cpu_s(proc.pid)
                for child in children_of(proc.pid):  # the firmware_sim subprocess
                    sim_cpu[child] = proc_cpu_s(child)
            time.sleep(0.2)
        code = proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    wall = time.monotonic() - t0
    reader.join(5)
    run = FindRun(time_scale, wall, code, cpu_find_s=find_cpu, cpu_sim_s=sum(sim_cpu.values()) or None)
    result = out / "result.json"
    if result.exists():
        r = json.loads(result.read_text())
        positions = r.get("positions", [])
        run.imu_lost = int(sum(p.get("lost_samples", 0) for p in positions))
        run.accel_lost = int(sum(p.get("accel_lost_samples", 0) for p in positions))
        run.device_s = r.get("duration_device_s")
    else:
        tail = stderr.decode("utf-8", "replace").strip().splitlines()
        run.error = tail[-1] if tail else f"exit {code}, no result.json"
    _read_gaps(run, out / "run" / "events.jsonl")
    if code != 0 and not run.error:
        run.error = f"exit {code}"
    shutil.rmtree(out, ignore_errors=True)
    return run


def find_available() -> str:
    """'' if `northfinder find --simulate` exists here, else why not."""
    p = subprocess.run([sys.executable, "-m", "northfinder", "find", "--help"], cwd=ROOT, env=ENV,
                       capture_output=True, text=True, timeout=60)
    if p.returncode != 0:
        return (p.stderr.strip().splitlines() or ["northfinder find --help failed"])[-1]
    if "--simulate" not in p.stdout or "--time-scale" not in p.stdout:
        return "northfinder find has no --simulate/--time-scale yet"
    return ""


def bench_find(scales: list[float], timeout_s: float, seed: int) -> tuple[list[Row], FindRun | None]:
    why = find_available()
    if why:
        return [Row("find 8 × 60 s end to end", "not available", why)], None
    rows, best = [], None
    for k in sorted(scales, reverse=True):
        r = run_find(k, timeout_s, seed)
        cpu = (f"CPU find {r.cpu_find_s:.1f} s, sim {r.cpu_sim_s:.1f} s" if r.cpu_sim_s is not None
               else f"CPU find {r.cpu_find_s:.1f} s")
        if r.imu_lost is None:
            note = f"failed: {r.error}; {cpu}"
        else:
            note = (f"lost IMU {r.imu_lost}, accel {r.accel_lost}; device {r.device_s:.1f} s measured; "
                    f"{cpu}; {r.gaps_note()}" + r.says())
        rows.append(Row(f"find 8 × 60 s at time scale {k:g}", f"{r.wall_s:.1f} s wall", note))
        print(f"  … time scale {k:g}: {r.wall_s:.1f} s wall, {note}", file=sys.stderr, flush=True)
        if r.kept_up:
            best = r
            break
    what = "find 8 × 60 s, largest scale this host keeps up with"
    if best is None:
        rows.append(Row(what, "none of the scales tried",
                        f"tried {', '.join(f'{k:g}' for k in sorted(scales, reverse=True))}"))
    else:
        rows.append(Row(what, f"{best.wall_s:.1f} s wall at {best.time_scale:g}×",
                        "0 IMU and 0 accelerometer samples lost, and the run did not say the host "
                        "fell behind (runs.find.pace_note)"))
    return rows, best


def profile_find(time_scale: float, timeout_s: float, seed: int, top: int = 18) -> str:
    """The find once more under cProfile (its main thread: sequencer, reads, estimator, report)."""
    prof = Path(tempfile.mkdtemp(prefix="nf-prof-")) / "find.prof"
    run = run_find(time_scale, timeout_s, seed, prefix=["-m", "cProfile", "-o", str(prof)])
    text = io.StringIO()
    print(f"cProfile of find at time scale {time_scale:g}: {run.wall_s:.1f} s wall, CPU find "
          f"{run.cpu_find_s:.1f} s, sim {run.cpu_sim_s or 0:.1f} s, lost IMU {run.imu_lost}, "
          f"accel {run.accel_lost} {run.error}", file=text)
    if prof.exists():
        stats = pstats.Stats(str(prof), stream=text)
        stats.sort_stats("tottime").print_stats(top)
        stats.sort_stats("cumulative").print_stats(top)
    else:
        print("(no profile written)", file=text)
    shutil.rmtree(prof.parent, ignore_errors=True)
    return text.getvalue()


def _sample_child(time_scale: float, seed: int, period_s: float = 0.005, top: int = 6) -> int:
    """Run find in this process with a stack sampler: per thread, its CPU seconds (from
    /proc/self/task/<tid>/stat) and the innermost functions it was seen in (wall samples, so
    waits show up as waits). cProfile sees only the main thread; the losses happen in the
    reader threads."""
    import collections
    import traceback

    from northfinder.cli import main as nf_main

    counts: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    totals: collections.Counter = collections.Counter()
    cpu_by_name: dict[str, float] = {}
    done = threading.Event()

    def thread_cpu(native_id: int) -> float | None:
        try:
            f = Path(f"/proc/self/task/{native_id}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            return None
        return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")

    def sampler() -> None:
        while not done.wait(period_s):
            threads = {t.ident: t for t in threading.enumerate()}
            for ident, frame in sys._current_frames().items():
                if ident == me_sampler[0]:
                    continue
                t = threads.get(ident)
                name = (t.name if t is not None else str(ident)).split(" ")[0]
                if t is not None and t.native_id is not None:
                    c = thread_cpu(t.native_id)
                    if c is not None:
                        cpu_by_name[f"{name} [{t.native_id}]"] = c
                leaf = traceback.extract_stack(frame, limit=1)[-1]
                ours = next((fs for fs in reversed(traceback.extract_stack(frame))
                             if "/site-packages/" not in fs.filename and "/lib/python3" not in fs.filename),
                            leaf)
                where = f"{Path(leaf.filename).name}:{leaf.name}"
                if ours is not leaf:
                    where += f"  (from {Path(ours.filename).name}:{ours.name})"
                counts[name][where] += 1
                totals[name] += 1

    me_sampler = [0]
    th = threading.Thread(target=sampler, name="sampler", daemon=True)
    th.start()
    me_sampler[0] = th.ident
    out = Path(tempfile.mkdtemp(prefix="nf-sample-"))
    t0, c0 = time.monotonic(), time.process_time()
    code = nf_main(find_cmd(time_scale, out, seed)[2:])
    wall, cpu = time.monotonic() - t0, time.process_time() - c0
    done.set()
    th.join()
    r = json.loads((out / "result.json").read_text()) if (out / "result.json").exists() else {}
    pos = r.get("positions", [])
    lost_imu = sum(p.get("lost_samples", 0) for p in pos)
    lost_acc = sum(p.get("accel_lost_samples", 0) for p in pos)
    print(f"\nsampled find at time scale {time_scale:g}: exit {code}, {wall:.1f} s wall, {cpu:.1f} s CPU "
          f"(this process, all threads), lost IMU {lost_imu}, accel {lost_acc}")
    print("CPU seconds per thread (the last reading of each thread seen alive):")
    for name, c in sorted(cpu_by_name.items(), key=lambda kv: -kv[1])[:10]:
        print(f"  {c:7.2f} s  {name}")
    print(f"where each thread was (share of {period_s * 1e3:g} ms wall samples):")
    for name, total in totals.most_common(8):
        print(f"  {name}  ({total} samples)")
        for where, k in counts[name].most_common(top):
            print(f"      {100 * k / total:5.1f} %  {where}")
    shutil.rmtree(out, ignore_errors=True)
    return 0


# --------------------------------------------------------------------------------------------


def _matching(run_gaps: list[int], reference: list[int]) -> int:
    """How many of a run's gaps equal the reference run's, position by position."""
    return sum(a == b for a, b in zip(run_gaps, reference, strict=False))


def bench_gaps(scales: str, timeout_s: float, seed: int) -> list[Row]:
    """One find per scale: the gaps between dwells in device time (unchanged from the first scale
    listed, 10× say, while the host keeps up: counted gap by gap, same seed and plan), the host's
    share (before_move_s), the wall time, the losses."""
    rows = []
    runs: dict[str, list[list[int]]] = {}  # each scale's runs' gaps [device s]
    walls: dict[str, list[float]] = {}
    reference: tuple[str, list[int]] | None = None  # the first run with gaps
    for text in (s.strip() for s in scales.split(",") if s.strip()):
        k = time_scale_arg(text)
        key = _scale_text(k)
        r = run_find(k, timeout_s, seed)
        run_gaps = [round(g) for g in r.gaps_s or []]
        lost = "failed" if r.imu_lost is None else f"lost IMU {r.imu_lost}, accel {r.accel_lost}"
        note = f"{lost}; {r.gaps_note()}" + r.says()
        if reference is None:
            reference = (key, run_gaps) if run_gaps else None
        else:
            ref_key, ref_gaps = reference
            note += f"; as at {ref_key}×: {_matching(run_gaps, ref_gaps)} of {len(ref_gaps)} gaps"
        rows.append(Row(f"find 8 × 60 s at {key}", f"{r.wall_s:.1f} s wall", note))
        print(f"  … {key}: {rows[-1].figure}, {rows[-1].note}", file=sys.stderr, flush=True)
        runs.setdefault(key, []).append(run_gaps)
        walls.setdefault(key, []).append(r.wall_s)
    for key, gap_lists in runs.items():
        g = [x for gaps in gap_lists for x in gaps]
        if len(gap_lists) < 2 or not g:
            continue
        values, counts = np.unique(g, return_counts=True)
        spread = ", ".join(f"{v:.0f} s ×{c}" for v, c in zip(values, counts, strict=True))
        as_ref = ""
        if reference is not None:
            compared = gap_lists[1:] if key == reference[0] else gap_lists  # not the reference itself
            if compared:
                as_ref = (f"; as at {reference[0]}×: {sum(_matching(x, reference[1]) for x in compared)} of "
                          f"{len(reference[1]) * len(compared)}")
        rows.append(Row(f"gaps at {key}, {len(gap_lists)} runs", f"median {np.median(g):.0f} s",
                        f"{spread}{as_ref}; wall {min(walls[key]):.1f}–{max(walls[key]):.1f} s"))
    return rows


def print_table(rows: list[Row]) -> None:
    w1 = max(len(r.what) for r in rows)
    w2 = max(len(r.figure) for r in rows)
    print(f"{'what':{w1}}  {'figure':{w2}}  note")
    print(f"{'-' * w1}  {'-' * w2}  {'-' * 4}")
    for r in rows:
        print(f"{r.what:{w1}}  {r.figure:{w2}}  {r.note}")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=200_000, help="frames in the decoder's stream")
    p.add_argument("--chunk-bytes", type=int, default=4096)
    p.add_argument("--driver-s", type=float, default=10.0, help="seconds of 1 kHz real-time streaming")
    p.add_argument("--imu-scales", default="50,100",
                   help="time scales at which to stream the IMU alone (is the IMU path lossless there?)")
    p.add_argument("--trials", type=int, default=10_000, help="Monte Carlo trials per batch")
    p.add_argument("--scales", default="100,50,20,15,10", help="time scales to try for find, comma-separated")
    p.add_argument("--find-timeout-s", type=float, default=300.0, help="wall limit per find run")
    p.add_argument("--gaps", metavar="SCALES", default=None,
                   help="only: one 8 × 60 s find at each scale (comma-separated, `auto` allowed) and its "
                   "device-time gaps between dwells, wall time and losses; each run's gaps are compared "
                   "gap by gap with the first scale's run (give 10 first: 'as at 10×: k of n')")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--skip-find", action="store_true")
    p.add_argument("--profile", action="store_true",
                   help="then profile one find at the lossless scale (or the smallest tried)")
    p.add_argument("--sample", type=float, metavar="K", default=None,
                   help="only: run one find at time scale K in-process under a per-thread stack sampler")
    p.add_argument("--sample-child", type=float, default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.sample_child is not None:
        return _sample_child(args.sample_child, args.seed)
    if args.sample is not None:  # a fresh process, so the sampler sees only the find
        return subprocess.call([sys.executable, __file__, "--sample-child", repr(args.sample),
                                "--seed", str(args.seed)], cwd=ROOT, env=ENV)

    for line in host_lines():
        print(line)
    print(flush=True)
    if args.gaps is not None:
        print_table(bench_gaps(args.gaps, args.find_timeout_s, args.seed))
        print(f"\nload avg  {' '.join(f'{x:.2f}' for x in os.getloadavg())} at the end")
        return 0
    rows = bench_decoder(args.frames, args.chunk_bytes)
    rows.append(bench_can())
    rows.append(bench_slcan_client())
    rows.append(bench_slcan_client(ChunkedSlcanBus))
    rows.append(bench_driver_cpu(args.driver_s))
    rows.append(bench_driver_cpu_with_can(args.driver_s))
    for k in [float(x) for x in args.imu_scales.split(",") if x.strip()]:
        rows.append(bench_driver_cpu(max(2.0, args.driver_s / 2), k))
    rows += bench_montecarlo(args.trials)
    best = None
    scales = [float(s) for s in args.scales.split(",") if s.strip()]
    if args.skip_find:
        rows.append(Row("find 8 × 60 s end to end", "skipped", "--skip-find"))
    else:
        find_rows, best = bench_find(scales, args.find_timeout_s, args.seed)
        rows += find_rows
    print_table(rows)
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"\nload avg  {load} at the end; CPU of this script "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_utime:.1f} s user")
    if args.profile and not args.skip_find and rows[-1].figure != "not available":
        k = best.time_scale if best is not None else min(scales)
        print()
        print(profile_find(k, args.find_timeout_s, args.seed))
    return 0


if __name__ == "__main__":
    sys.exit(main())
