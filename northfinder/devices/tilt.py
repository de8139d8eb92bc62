"""The tilt-sensor role: an accelerometer (inclinometer) streaming device-indexed specific-force
samples with a counter, started and stopped by command (CANopen NMT for our node).

:meth:`TiltSensor.resume` is the start after a move, built once here: it drops everything the
sensor sent before its last stop — decided in device order when the model can prove the stop (a
heartbeat reporting "stopped"), else by host quiet, which the events log then says.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from northfinder.errors import DeviceError

ROLE = "accelerometer"
STOPPED_REPORT_WAIT_S = 2.5
"""Host seconds to wait for the sensor's proof that it stopped (our node: a heartbeat reporting
stopped, which normally arrived during the move: 1 s producer time, PROTOCOLS.md §3.1 object 1017)
— only a bound of the wait."""


@dataclass(frozen=True)
class AccelBlock:
    """Consecutive samples. `lost_samples` counts gaps inside the block."""

    counter: np.ndarray  # int64 [n], unwrapped device counter
    accel_g: np.ndarray  # float64 [n, 3]
    temperature_c: np.ndarray  # float64 [n]
    status: np.ndarray  # uint8 [n]
    lost_samples: int

    def __len__(self) -> int:
        return len(self.counter)


class TiltDecoder(ABC):
    """A model's pure decoder of its raw log (replay)."""

    @abstractmethod
    def decode_log(self, path: Path, settings: dict[str, Any]) -> AccelBlock | None:
        """The log at `path` → every sample (None when the file is missing); `settings` is the run's
        recorded `accelerometer` start entry."""


class TiltSensor(ABC):
    """A streaming accelerometer; a context manager. A model implements the abstract methods (and
    sets `port`, `rate_hz`)."""

    role = ROLE
    port: str | None = None
    model_name: str = ""
    """The registry name of the model (set by registry.open_device)."""
    rate_hz: float
    _silent_at: int | None = None
    """Status-report count when the last wait for the stop's proof timed out (None: it did not)."""
    stop_reported: bool = False
    """The last :meth:`resume` found the sensor's report that it had stopped: its stops are proven
    in device order, so a dwell may be read `until_stopped` after the next move was commanded."""

    @abstractmethod
    def read(self, n_samples: int, timeout_s: float | None = None, until_stopped: bool = False) -> AccelBlock:
        """The next `n_samples` samples (DeviceError after `timeout_s`). `until_stopped`: fewer when
        the sensor's report that it stopped (after the last stop_stream) comes first — then the block
        holds every sample it sent before stopping (a model without such a report waits for all)."""

    @abstractmethod
    def discard_pending(self) -> int: ...

    @abstractmethod
    def pending_samples(self) -> int:
        """Samples received and not read yet."""

    @abstractmethod
    def start_stream(self) -> None:
        """Make the sensor send samples (NMT start)."""

    @abstractmethod
    def stop_stream(self) -> None:
        """Make the sensor stop sending samples (NMT stop)."""

    @abstractmethod
    def wait_stopped_report(self, timeout_s: float) -> bool:
        """Wait for the sensor's own report, after the last stop, that it stopped — it then comes after
        every sample sent before (device order). False after timeout_s or if the model has none."""

    @abstractmethod
    def status_reports(self) -> int:
        """Status reports (heartbeats) received so far."""

    @abstractmethod
    def fault_reports(self) -> list[dict[str, Any]]:
        """The sensor's fault messages so far (EMCY: code, register, meaning)."""

    @abstractmethod
    def flush_log(self) -> None:
        """Push the raw log to disk."""

    @abstractmethod
    def identity(self) -> dict[str, Any]: ...

    @abstractmethod
    def configure_for_run(self, section: Any, log_event: Callable[[dict[str, Any]], None]) -> dict[str, Any]:
        """Start-of-run configuration from the bench section; returns what the start event records
        (identity and what the decoder needs)."""

    @abstractmethod
    def close(self) -> None: ...

    @property
    def stats(self) -> Any:
        raise NotImplementedError

    # -- built once on top -------------------------------------------------------------------
    def check_line(self) -> str:
        """`northfinder check`'s line for this device: what answered and what it says it is (a model
        may say more: its state, its data)."""
        ident = ", ".join(f"{k} {v}" for k, v in self.identity().items())
        return f"{self.role} on {self.port}: {ident}"

    def pause(self) -> None:
        """Quiet during a move."""
        self.stop_stream()

    def resume(self, check_stop: Callable[[], None], log_event: Callable[[dict[str, Any]], None],
               quiet_s: float = 0.1, timeout_s: float = 10.0,
               before_start: Callable[[], None] | None = None) -> None:
        """Start again once everything sent before the last stop has arrived (and is dropped);
        `before_start` is called just before the start command (the caller notes the moment).

        A sensor whose stop report is off or lost (none within STOPPED_REPORT_WAIT_S; not waited for
        again until a report comes back): the link is drained until nothing arrives for quiet_s —
        host time, and the events log says so."""
        reports = self.status_reports()
        waited = self._silent_at != reports and self.wait_stopped_report(STOPPED_REPORT_WAIT_S)
        self.stop_reported = waited
        if waited:
            self._silent_at = None
            self.discard_pending()
            if before_start is not None:
                before_start()
            self.start_stream()
            return
        if self._silent_at != reports:
            log_event({"event": "accel_drain", "by": "host quiet",
                       "why": "no heartbeat reported the node stopped"})
        self._silent_at = self.status_reports()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            check_stop()
            if self.discard_pending() == 0:
                time.sleep(quiet_s)
                if self.discard_pending() == 0:
                    break
            else:
                time.sleep(0.02)
        if before_start is not None:
            before_start()
        self.start_stream()

    def read_until_stopped(self, n: int, log_event: Callable[[dict[str, Any]], None],
                           quiet_s: float = 0.1) -> AccelBlock:
        """Up to `n` samples, after a stop: all the sensor sent before it, once its report that it
        stopped is here (device order). Without that report within STOPPED_REPORT_WAIT_S: those that
        came until nothing more arrived for quiet_s — host time, and the events log says so."""
        try:
            return self.read(n, timeout_s=STOPPED_REPORT_WAIT_S, until_stopped=True)
        except DeviceError:
            pass
        log_event({"event": "accel_drain", "by": "host quiet",
                   "why": "no heartbeat reported the node stopped after its dwell"})
        last = -1
        while (now := self.pending_samples()) != last and now < n:
            last = now
            time.sleep(quiet_s)
        if now == 0:
            return AccelBlock(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.uint8), 0)
        return self.read(min(n, now), timeout_s=quiet_s)

    def read_samples(self, n: int, read_timeout_s: float) -> AccelBlock:
        """`read` bounded by the samples' own duration (twice) plus `read_timeout_s` host seconds."""
        return self.read(n, timeout_s=max(read_timeout_s, 2.0 * n / self.rate_hz + read_timeout_s))

    def counts(self) -> tuple[int, int]:
        """(status reports, fault messages) so far: a dwell's share is the difference."""
        return self.status_reports(), len(self.fault_reports())

    def counters(self) -> dict[str, Any]:
        """The counters for the events log's `stats` event."""
        st = self.stats
        return {"accel": st.as_dict() if hasattr(st, "as_dict") else dict(vars(st)),
                "emergencies": self.fault_reports()}

    def __enter__(self) -> TiltSensor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
