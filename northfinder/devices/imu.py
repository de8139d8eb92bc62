"""The inertial-stream role: an IMU that streams device-indexed samples (gyro, accelerometer).

:class:`ImuBlock` and :class:`ImuAxes` are the data every IMU model produces, live and in replay;
:class:`InertialStream` is what the sequencer and the runs call; :class:`ImuDecoder` is a model's
pure decoder of its raw log, which replay gets from the registry by the model recorded in the run.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from northfinder.errors import DeviceError

ROLE = "imu"


@dataclass(frozen=True)
class ImuAxes:
    """Which axes a unit has: six booleans, gyro x y z then accelerometer x y z."""

    present: tuple[bool, bool, bool, bool, bool, bool]

    @classmethod
    def from_valid(cls, valid: np.ndarray) -> ImuAxes:
        """Axes valid in at least half of the given samples (bool [n, 6]): a unit that flags a sample
        now and then keeps its axes."""
        mask = np.asarray(valid, dtype=bool)
        return cls(tuple(bool(2 * c >= len(mask)) for c in mask.sum(axis=0)))  # type: ignore[arg-type]

    @property
    def gyro(self) -> str:
        """The gyro axes, e.g. "y" or "xyz"."""
        return "".join(a for a, p in zip("xyz", self.present[:3], strict=True) if p)

    @property
    def accel(self) -> str:
        """The accelerometer axes, e.g. "" or "xyz"."""
        return "".join(a for a, p in zip("xyz", self.present[3:], strict=True) if p)

    def describe(self) -> str:
        """"gyro y only", "gyro x y z, no accel", "gyro x y z, accel x y z"."""
        g = " ".join(self.gyro) or "none"
        if not self.accel:
            return f"gyro {g} only" if len(self.gyro) == 1 else f"gyro {g}, no accel"
        return f"gyro {g}, accel {' '.join(self.accel)}"


ALL_AXES = ImuAxes((True,) * 6)  # type: ignore[arg-type]


@dataclass(frozen=True)
class ImuBlock:
    """Consecutive decoded samples. `lost_samples` counts gaps inside the block.

    A field the model flags not valid (or an axis the unit does not have) is NaN in `gyro_rad_s` /
    `accel_g`, so it is excluded from every mean, never averaged."""

    sample_index: np.ndarray  # int64 [n], device sample count
    gyro_rad_s: np.ndarray  # float64 [n, 3], NaN where not valid
    accel_g: np.ndarray  # float64 [n, 3], NaN where not valid
    status: np.ndarray  # uint8 [n], the model's own status byte
    temperature_c: np.ndarray  # float64 [n]
    lost_samples: int
    rate_hz: float
    unknown_gaps: tuple[int, ...] = ()
    """Index of the first sample after each gap whose length is unknown (a wrapping counter that
    lost more than one period): the time of every later sample is known only up to that period."""

    @property
    def valid(self) -> np.ndarray:
        """bool [n, 6]: each axis's validity (gyro x y z, accel x y z)."""
        return np.isfinite(np.hstack([self.gyro_rad_s, self.accel_g]))

    @property
    def time_s(self) -> np.ndarray:
        """Device time of each sample: sample_index / rate_hz."""
        return self.sample_index / self.rate_hz

    def __len__(self) -> int:
        return len(self.sample_index)


class ImuDecoder(ABC):
    """A model's pure decoder of its raw IMU log (replay, and the runs' log readers)."""

    @abstractmethod
    def decode_log(self, raw: bytes, settings: dict[str, Any]) -> tuple[ImuBlock, Any]:
        """The whole log → one block (as the live driver returned it) and the stream's counters;
        `settings` is the run's recorded `imu` start entry (rate_hz and the model's own keys)."""

    @abstractmethod
    def index_chunks(self, chunks: Sequence[bytes]) -> list[np.ndarray]:
        """Feed the log chunk by chunk (as it arrived): the device sample indices each chunk completed."""

    @abstractmethod
    def first_counter(self, raw: bytes) -> int:
        """The model's own sample counter of the log's first sample (to place it on the device clock)."""

    counter_period: int = 0
    """Samples after which the model's counter wraps (0: it does not)."""
    counter_name: str = "sample counter"
    """The model's name for its counter, in its manual's words (a result's note on an unknown gap
    names it)."""


class InertialStream(ABC):
    """An IMU streaming samples; a context manager. A model implements the abstract methods (and sets
    `port`, `rate_hz`); the reconnect, the timed read and the counters are built once here."""

    role = ROLE
    port: str | None = None
    model_name: str = ""
    """The registry name of the model (set by registry.open_device)."""
    rate_hz: float
    reconnects: int = 0
    gyro_range_dps: float | None = None
    """The gyros' input range [°/s] (±), as the model's data sheet gives it; None: not known (a run
    then cannot say a sway saturates it before the estimator does)."""

    # -- what a model implements -------------------------------------------------------------
    @abstractmethod
    def read(self, n_samples: int, timeout_s: float | None = None) -> ImuBlock:
        """The next n samples (blocks until they are there; DeviceError on time-out)."""

    @abstractmethod
    def discard_pending(self) -> int:
        """Drop samples decoded but not read yet; returns how many."""

    @abstractmethod
    def identity(self) -> dict[str, Any]:
        """What the unit says it is (model, serial, firmware …) as far as the protocol tells."""

    @abstractmethod
    def recorded_settings(self) -> dict[str, Any]:
        """What the run records for the decoder to replay the raw log (rate_hz and the model's keys)."""

    @abstractmethod
    def configure_for_run(self, rate_hz: float | None) -> None:
        """Start-of-run configuration: read back what the decoder must know; set the rate if asked."""

    @abstractmethod
    def close(self) -> None: ...

    @property
    def axes(self) -> ImuAxes:
        """The axes the unit has (a model that cannot tell has all six)."""
        return ALL_AXES

    @property
    def stats(self) -> Any:
        """The stream's counters (an object with `as_dict()`)."""
        raise NotImplementedError

    @property
    def failed(self) -> BaseException | None:
        """The error that stopped the stream (port gone), or None while it runs."""
        return None

    @property
    def stall_indices(self) -> list[int]:
        """First sample index after each pause of unknown length."""
        return []

    def start_tap(self) -> bool:
        """Keep every sample decoded from now on, read or not, for :meth:`take_tapped` (a run's
        per-sample fit sees the whole stream, not the pieces the sequencer reads). False when the
        model cannot: the run then decodes its raw log."""
        return False

    @property
    def first_sample_index(self) -> int | None:
        """The device index of the first sample decoded since the link opened (None: none yet, or
        the model does not say)."""
        return None

    def take_tapped(self) -> ImuBlock | None:
        """The samples decoded since the last call (after start_tap), in stream order and exactly
        as the model's decoder gives them from the raw log; None when the model does not tap."""
        return None

    def newest_index(self) -> int | None:
        """Device index of the newest sample decoded, read or not (None: none yet, or the model
        cannot tell): at this host moment the unit's clock is at least there — behind it by the
        link's latency, never ahead."""
        return None

    def caught_up_index(self, timeout_s: float) -> int | None:
        """Like :meth:`newest_index`, taken when the reader has next read everything the unit sent
        (at most `timeout_s` host seconds from now): a lower bound of the unit's clock that does
        not lag by a backlog. A model that cannot tell: the newest index."""
        return self.newest_index()

    def next_index(self, timeout_s: float) -> int | None:
        """Device index of the sample the next :meth:`read` returns, waiting at most `timeout_s`
        host seconds for one, reading nothing; None when the model cannot tell."""
        return None

    def wait_decoded(self, n: int, timeout_s: float) -> bool | None:
        """Wait until `n` more samples have been decoded (read or not), at most `timeout_s` host
        seconds: True when they came, False on time-out; None when the model cannot tell (then
        :meth:`wait_device_s` stands host time for device time)."""
        return None

    def reopen(self, timeout_s: float) -> int:
        """Re-open a vanished link; returns the attempts it took (DeviceError if not within timeout_s)."""
        raise DeviceError(ROLE, self.port, "this IMU model cannot re-open its link")

    # -- built once on top -------------------------------------------------------------------
    def check_line(self) -> str:
        """`northfinder check`'s line for this device: what answered and what it says it is (a model
        may say more: its state, its data)."""
        ident = ", ".join(f"{k} {v}" for k, v in self.identity().items())
        return f"{self.role} on {self.port}: {ident}"

    def has_gyro_z(self) -> bool:
        return "z" in self.axes.gyro

    def read_samples(self, n: int, read_timeout_s: float) -> ImuBlock:
        """`read` bounded by the samples' own duration (twice) plus `read_timeout_s` host seconds."""
        wait_s = 2.0 * n / self.rate_hz + read_timeout_s
        return self.read(n, timeout_s=max(read_timeout_s, wait_s))

    def wait_device_s(self, device_s: float, host_max_s: float) -> None:
        """Let `device_s` of the unit's own time go by, judged by its samples arriving, for at most
        `host_max_s` host seconds: a poll paced this way keeps its period in device time whatever
        the host's speed or the simulator's time scale (issue 27)."""
        n = max(1, int(round(device_s * float(self.rate_hz))))
        if self.wait_decoded(n, host_max_s) is None:
            time.sleep(min(device_s, host_max_s))

    def recover(self, timeout_s: float) -> dict[str, Any] | None:
        """After a failed read: re-open the link if it vanished (None when it did not — the read just
        timed out); returns how it went for the events log; DeviceError if it stays gone."""
        if self.failed is None:
            return None
        t0 = time.monotonic()
        attempts = self.reopen(timeout_s)
        return {"attempts": attempts, "wall_s": round(time.monotonic() - t0, 3)}

    def counters(self) -> dict[str, Any]:
        """The stream's counters for the events log's `stats` event."""
        st = self.stats
        return {"imu": st.as_dict() if hasattr(st, "as_dict") else dict(vars(st)),
                "imu_reconnects": int(self.reconnects), "imu_stalls": len(self.stall_indices),
                "imu_axes": self.axes.gyro, "imu_accel_axes": self.axes.accel}

    def __enter__(self) -> InertialStream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
