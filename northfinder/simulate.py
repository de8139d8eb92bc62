"""Start firmware-sim as a subprocess and wire its endpoints into a bench configuration.

northfinder never imports firmware_sim: it runs `python -m firmware_sim` (the same interpreter),
reads the one JSON line of endpoints it prints, and terminates it at the end.
"""

from __future__ import annotations

import json
import os
import selectors
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from northfinder.config import BenchConfig
from northfinder.errors import DeviceError, InputError

FIRMWARE_SIM_USAGE_EXIT = 2
"""firmware-sim's exit code when it refuses its command line (a fault, grade or value it does not
know), before it opens any device: northfinder passes that on as its own usage error (exit 2)."""


def _arg(value: Any) -> str:
    """A flag's value as firmware-sim reads it: floats exactly (repr), vectors as X,Y,Z."""
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, tuple | list):
        return ",".join(repr(float(v)) for v in value)
    return str(value)


def firmware_sim_argv(options: dict[str, Any], faults: Sequence[str] = ()) -> list[str]:
    """`python -m firmware_sim` with `options` ({flag: value}, in order; None left out) and
    one `--fault` per fault: the one place every scenario's command line is built."""
    out = [sys.executable, "-m", "firmware_sim"]
    for flag, value in options.items():
        if value is not None:
            out += [flag, _arg(value)]
    for fault in faults:
        out += ["--fault", fault]
    return out


def _flag_value(value: Any, kind: str) -> Any:
    """A field as its flag takes it: "float"/"int" (None stays None), "opt" (empty → left out),
    "unless=V" (V, firmware-sim's default, left out)."""
    if kind == "float":
        return None if value is None else float(value)
    if kind == "int":
        return None if value is None else int(value)
    if kind == "opt":
        return value or None
    if kind.startswith("unless="):  # firmware-sim's own default is left out of its command line
        return None if value == kind.removeprefix("unless=") else value
    return value


class SimScenario:
    """The one simulator-settings type: a scenario's settings (a dataclass subclass) say which field
    goes to which firmware-sim flag (`FLAGS`: field, flag, kind) and what a run records of them
    (`RECORDED`); the command line and the record are built here, once."""

    scenario: ClassVar[str | None] = None
    """firmware-sim's --scenario; None for its default, the bench."""
    FLAGS: ClassVar[tuple[tuple[str, str, str], ...]] = ()
    RECORDED: ClassVar[tuple[str, ...]] = ()
    faults: Sequence[str]

    def argv(self) -> list[str]:
        """The firmware-sim command line for these settings."""
        options: dict[str, Any] = {"--scenario": self.scenario} if self.scenario else {}
        for name, flag, kind in self.FLAGS:
            options[flag] = _flag_value(getattr(self, name), kind)
        return firmware_sim_argv(options, self.faults)

    def to_dict(self) -> dict[str, Any]:
        """What config.json and the start event record of the simulated run."""
        out: dict[str, Any] = {"scenario": self.scenario}
        for name in self.RECORDED:
            value = getattr(self, name)
            out[name] = list(value) if isinstance(value, tuple | list) else value
        return out


@dataclass
class SimSettings(SimScenario):
    """The bench scenario: the truth and the knobs passed on to firmware-sim (degrees at the edge)."""

    FLAGS: ClassVar[tuple[tuple[str, str, str], ...]] = (
        ("heading_deg", "--heading", "float"), ("pitch_deg", "--pitch", "float"),
        ("roll_deg", "--roll", "float"),
        ("latitude_deg", "--latitude", "float"), ("grade", "--grade", ""), ("seed", "--seed", "int"),
        ("time_scale", "--time-scale", "float"), ("config", "--config", "opt"), ("can", "--can", "opt"),
        ("stage_model", "--stage", "unless=smc100"), ("imu_model", "--imu", "unless=kvh"),
        ("tilt_model", "--tilt", "unless=nf-accel"),
    )

    heading_deg: float = 37.0
    pitch_deg: float = 1.5
    roll_deg: float = -0.8
    latitude_deg: float = 40.0
    grade: str = "nav"
    seed: int = 1
    time_scale: float = 20.0
    faults: Sequence[str] = field(default_factory=tuple)
    config: str | None = None
    can: str | None = None
    """Where firmware-sim puts its CAN node, INTERFACE[:CHANNEL] (None: its slcan adapter on a pty)."""
    stage_model: str = "smc100"
    imu_model: str = "kvh"
    tilt_model: str = "nf-accel"
    """The simulated devices' models (firmware-sim --stage/--imu/--tilt; bench.toml's `model =` names)."""
    paced: bool = False
    """The client paces the time scale (find --time-scale auto): firmware-sim reads `time-scale K`
    lines on its standard input (--control-stdin); `time_scale` is then the highest it will be asked
    for, which sizes firmware-sim's buffers."""

    def argv(self) -> list[str]:
        return super().argv() + (["--control-stdin"] if self.paced else [])

    def truth(self) -> dict[str, float]:
        return {
            "heading_deg": float(self.heading_deg) % 360.0,
            "pitch_deg": float(self.pitch_deg),
            "roll_deg": float(self.roll_deg),
            "latitude_deg": float(self.latitude_deg),
        }


class SimulatorProcess:
    """`with SimulatorProcess(settings) as endpoints:` — firmware-sim runs for the block's duration.

    `required_endpoints` names the keys the scenario must print (the bench's turntable; a ship's
    or a vehicle's IMU and GNSS — subclasses set it).
    """

    required_endpoints: tuple[str, ...] = ("turntable",)
    scenario_name = "bench"

    def __init__(self, settings: SimSettings, *, startup_timeout_s: float = 30.0):
        self.settings = settings
        self.startup_timeout_s = startup_timeout_s
        self.proc: subprocess.Popen[bytes] | None = None
        self.endpoints: dict[str, Any] = {}

    def start(self) -> dict[str, Any]:
        """Start the process and return its endpoints; a clear DeviceError if it fails to start."""
        env = dict(os.environ)
        env.setdefault("PYTHONUNBUFFERED", "1")
        # firmware_sim sits next to the northfinder package in a checkout: findable from any
        # working directory even when the project is not installed
        root = Path(__file__).resolve().parents[1]
        if (root / "firmware_sim").is_dir():
            env["PYTHONPATH"] = os.pathsep.join(p for p in (str(root), env.get("PYTHONPATH", "")) if p)
        try:
            # Own process group: a Ctrl-C in the terminal reaches northfinder only, which then stops
            # the stage through the simulator before it terminates it.
            self.proc = subprocess.Popen(
                self.settings.argv(),
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                stdin=subprocess.PIPE if self.paced else subprocess.DEVNULL,
                env=env,
                start_new_session=True,
            )
        except OSError as exc:
            raise DeviceError("firmware-sim", None, f"cannot start it ({exc.strerror})") from None
        line = self._read_line(self.startup_timeout_s)
        try:
            endpoints = json.loads(line)
            if not isinstance(endpoints, dict) or any(k not in endpoints for k in self.required_endpoints):
                raise ValueError
        except ValueError:
            self.stop()
            raise DeviceError(
                "firmware-sim", None,
                f"printed {line[:120]!r} instead of the {self.scenario_name} scenario's endpoints",
            ) from None
        self.endpoints = endpoints
        return endpoints

    @property
    def paced(self) -> bool:
        return bool(getattr(self.settings, "paced", False))

    def set_time_scale(self, scale: float) -> None:
        """Device time runs `scale`× the wall clock from now on (a paced simulator only)."""
        assert self.proc is not None and self.proc.stdin is not None, "not a paced simulator"
        try:
            self.proc.stdin.write(f"time-scale {float(scale)!r}\n".encode())
            self.proc.stdin.flush()
        except (BrokenPipeError, ValueError):
            pass  # it has exited: the run notices its devices gone

    def _read_line(self, timeout_s: float) -> str:
        assert self.proc is not None and self.proc.stdout is not None
        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        buf = b""
        deadline = time.monotonic() + timeout_s
        fd = self.proc.stdout.fileno()
        try:
            while b"\n" not in buf:
                left = deadline - time.monotonic()
                if left <= 0:
                    self.stop()
                    raise DeviceError(
                        "firmware-sim",
                        None,
                        f"printed no endpoints within {timeout_s:.0f} s; is firmware_sim installed?",
                    )
                if not sel.select(left):
                    continue
                chunk = os.read(fd, 4096)
                if not chunk:
                    err = self._stderr_tail()
                    usage = self.proc.returncode == FIRMWARE_SIM_USAGE_EXIT
                    self.stop()
                    if usage:  # its own flag check refused a value passed on: a usage error, not a device's
                        raise InputError(f"--simulate: {err.removeprefix('firmware-sim: ')}")
                    raise DeviceError("firmware-sim", None, f"exited before it was ready: {err}")
                buf += chunk
        finally:
            sel.close()
        return buf.split(b"\n", 1)[0].decode("utf-8", "replace").strip()

    def _stderr_tail(self) -> str:
        assert self.proc is not None and self.proc.stderr is not None
        try:
            self.proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            return "(no message)"
        lines = [ln for ln in self.proc.stderr.read().decode("utf-8", "replace").splitlines() if ln.strip()]
        return lines[-1].strip() if lines else f"exit code {self.proc.returncode}"

    def stop(self, timeout_s: float = 10.0) -> int | None:
        """SIGTERM, wait, SIGKILL if it does not go; returns its exit code."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            try:
                self.proc.send_signal(signal.SIGTERM)
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        for pipe in (self.proc.stdin, self.proc.stdout, self.proc.stderr):
            if pipe is not None:
                pipe.close()
        return self.proc.returncode

    def __enter__(self) -> dict[str, Any]:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()


def bench_config(
    endpoints: dict[str, Any], latitude_deg: float, base: BenchConfig | None = None
) -> BenchConfig:
    """A BenchConfig pointing at the simulator's endpoints (everything else from `base`)."""
    cfg = base or BenchConfig(source="--simulate")
    cfg.source = "--simulate"
    cfg.turntable.port = str(endpoints["turntable"])
    cfg.imu.port = str(endpoints["imu"])
    can = endpoints.get("can") or {}
    cfg.accelerometer.interface = str(can.get("interface", "slcan"))
    cfg.accelerometer.channel = str(can.get("channel", ""))
    cfg.accelerometer.bitrate = int(can.get("bitrate", cfg.accelerometer.bitrate))
    cfg.accelerometer.node_id = int(can.get("node_id", cfg.accelerometer.node_id))
    if "rate_hz" in can:
        cfg.accelerometer.rate_hz = float(can["rate_hz"])
    cfg.site.latitude_deg = float(latitude_deg)
    return cfg.validate()
