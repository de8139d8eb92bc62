"""What a USB-serial link between a device and its host does to the bytes: latency and hold-backs.

A `LinkShaper` sits between a device and its `PtyPort`. The device hands it each message with the
device time it was produced; the shaper writes it to the pty when it is due. Two effects:

- latency (`--link-latency MS,JITTER_MS`): a message produced at device time t is due at
  t + d(t), d(t) = MS ± JITTER_MS of DEVICE time. The jitter is a seeded process, not a draw per
  message: d takes a value uniform in [MS − J, MS + J] at knots every KNOT_JITTERS·J of device time
  and is linear in between, so d changes by at most 2J per 4J and t + d(t) always increases —
  latency never reorders bytes, and its mean stays MS at any message rate (independent draws
  per message, held in order, would pile up near MS + J at 1000 Hz).
- hold (`--link-hold PERIOD_S,HOLD_MS`): at device times PERIOD_S, 2·PERIOD_S, … (± an optional
  seeded jitter) the link stops writing for HOLD_MS of HOST WALL-CLOCK time, as a USB-serial adapter
  on a busy host does, then writes everything it held in one burst. A hold start that falls inside
  a hold (PERIOD_S shorter than the hold in device time) is skipped.

Nothing is ever lost or reordered here; bytes go to the port in the order they came. The shaper is
pumped once per loop tick, so a due time is met to within one tick (TICK_WALL_S × time_scale of
device time, at most TICK_DEVICE_S). The hold is the one place in firmware_sim that reads the wall
clock on purpose: what it models is a host-side stall, not a device behaviour.
"""

from __future__ import annotations

import collections
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

KNOT_JITTERS = 4.0
"""The jitter's knots are this many jitter amplitudes apart in device time (> 2 keeps the order)."""


@dataclass(frozen=True)
class LinkSpec:
    """One link's settings: latency (device s), its jitter (device s), hold period (device s) and
    hold length (wall s); a zero latency and a None hold mean the effect is off."""

    latency_s: float = 0.0
    jitter_s: float = 0.0
    hold_period_s: float | None = None
    hold_wall_s: float = 0.0
    hold_jitter_s: float = 0.0

    @property
    def active(self) -> bool:
        return self.latency_s > 0.0 or self.jitter_s > 0.0 or self.hold_period_s is not None


class LinkShaper:
    """Delays and holds a device's outgoing messages on their way to the pty (see module doc)."""

    def __init__(self, spec: LinkSpec, rng: np.random.Generator, *,
                 wall_clock: Callable[[], float] = time.monotonic,
                 on_event: Callable[[str, float, dict[str, Any]], None] | None = None,
                 name: str = "link") -> None:
        self.spec = spec
        self.rng = rng
        self.wall_clock = wall_clock
        self.on_event = on_event
        self.name = name
        self._knots = np.zeros(0)  # d at device times j·knot_s for j = _knot0, _knot0 + 1, …
        self._knot0 = 0
        self._queue: collections.deque[tuple[float, bytes]] = collections.deque()
        self._last_due_s = -math.inf
        self._next_hold_s = self._draw_hold_start(0.0) if spec.hold_period_s is not None else math.inf
        self._hold_until_wall: float | None = None
        self.holds = 0
        self.bytes_in = 0
        self.bytes_out = 0
        self.bytes_discarded = 0
        """Queued bytes forgotten because the client left (it would not have heard them)."""

    def _draw_hold_start(self, after_s: float) -> float:
        jitter = self.spec.hold_jitter_s
        offset = self.rng.uniform(-jitter, jitter) if jitter > 0.0 else 0.0
        return after_s + self.spec.hold_period_s + offset  # type: ignore[operator]

    def delay_s(self, t_device_s: np.ndarray) -> np.ndarray:
        """d(t): the latency of a message produced at device times t (see module doc)."""
        t = np.asarray(t_device_s, dtype=float)
        j_spec = self.spec.jitter_s
        if j_spec <= 0.0:
            return np.full(t.shape, self.spec.latency_s)
        knot_s = KNOT_JITTERS * j_spec
        need = int(math.floor(max(float(t.max()), 0.0) / knot_s)) + 2  # knots 0 … need−1, in order
        have = self._knot0 + len(self._knots)
        if need > have:
            more = self.rng.uniform(-j_spec, j_spec, need - have) + self.spec.latency_s
            self._knots = np.concatenate([self._knots, more])
        d = np.interp(t, (self._knot0 + np.arange(len(self._knots))) * knot_s, self._knots)
        drop = min(int(math.floor(max(float(t.min()), 0.0) / knot_s)) - self._knot0, len(self._knots) - 2)
        if drop > 0:  # times only grow: the knots before this call's first message are history
            self._knots, self._knot0 = self._knots[drop:], self._knot0 + drop
        return d

    @property
    def queued_bytes(self) -> int:
        return self.bytes_in - self.bytes_out - self.bytes_discarded

    def send(self, data: bytes, t_device_s: float) -> None:
        """One message produced at device time t (a reply, one NMEA epoch)."""
        self.send_many(data, np.array([len(data)]), np.array([t_device_s]))

    def send_many(self, data: bytes, sizes: np.ndarray, t_device_s: np.ndarray) -> None:
        """Consecutive messages (sizes in bytes, production times in device s) in one buffer."""
        if not data:
            return
        t = np.asarray(t_device_s, dtype=float)
        due = t + self.delay_s(t)
        due = np.maximum.accumulate(np.concatenate([[self._last_due_s], due]))[1:]  # (a guard: d keeps order)
        self._last_due_s = float(due[-1])
        ends = np.cumsum(sizes)
        starts = ends - sizes
        view = memoryview(data)
        if self.spec.latency_s == 0.0 and self.spec.jitter_s == 0.0:  # hold only: one entry
            self._queue.append((float(due[-1]), bytes(data)))
        else:
            for d, a, b in zip(due.tolist(), starts.tolist(), ends.tolist(), strict=True):
                self._queue.append((d, bytes(view[a:b])))
        self.bytes_in += len(data)

    def pump(self, t_device_s: float, port: Any) -> None:
        """Write to `port` every queued message due by device time t, unless the link is held."""
        if self._hold_until_wall is not None:
            if self.wall_clock() < self._hold_until_wall:
                return
            self._hold_until_wall = None
            while self._next_hold_s <= t_device_s < math.inf:  # starts inside the hold are skipped
                self._next_hold_s = self._draw_hold_start(self._next_hold_s)
            self._event("link_release", t_device_s, queued_bytes=self.queued_bytes)
        elif t_device_s >= self._next_hold_s:
            self._hold_until_wall = self.wall_clock() + self.spec.hold_wall_s
            self.holds += 1
            self._event("link_hold", t_device_s, hold_ms=self.spec.hold_wall_s * 1e3,
                        queued_bytes=self.queued_bytes)
            return
        out = bytearray()
        while self._queue and self._queue[0][0] <= t_device_s:
            out += self._queue.popleft()[1]
        if out:
            self.bytes_out += len(out)
            port.write(bytes(out))

    def discard(self) -> None:
        """Forget the queued bytes (the client left: what it had not received goes nowhere)."""
        self.bytes_discarded += self.queued_bytes
        self._queue.clear()

    def _event(self, name: str, t_device_s: float, **fields: Any) -> None:
        if self.on_event is not None:
            self.on_event(name, t_device_s, {"link": self.name, **fields})
