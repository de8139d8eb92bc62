"""The per-sample fit fed as the samples arrive: live from the IMU's tap, in replay from the decoded
log in chunks — one accumulator, one order of calls, so both give the same numbers bit for bit.

The find's per-sample fit (runs/find_motion.py, docs/estimators.md §10) takes every gyro sample of
the run. Holding them all grows with the run (~480 bytes a sample); `MotionFitAccumulator` keeps one
plan step of samples and a small triangular factor per stretch (issue 27, item 5). What feeds it:

- the samples, every one the IMU decoded (`InertialStream.start_tap`/`take_tapped`), not the
  pieces the sequencer reads; live they are taken from the tap at each dwell event, in replay the
  decoded imu.raw is pushed in `REPLAY_CHUNK` pieces — the accumulator's result does not depend on
  the chunking (a stretch is folded when its closing dwell arrives, from the same arrays);
- the dwells: each `position` event and the `returned` one, in the events log's order (failed
  attempts log no position event, so they never reach it).

A one-session run only: a resumed run joins sessions (runs/find_motion.py decodes its logs).
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Sequence
from typing import Any

import numpy as np

from northfinder.constants import DPH
from northfinder.devices.imu import ImuBlock, InertialStream
from northfinder.errors import InputError
from northfinder.estimators.motion_fit import RUN_TERMS, MotionFitAccumulator

DWELL_EVENTS = ("position", "returned")
"""The events that close a rest the fit is pinned to (their `imu` first/last index, table angle)."""
REPLAY_CHUNK = 4096
"""Samples pushed at a time in replay (any size gives the same result; this bounds the copies)."""
AXES = ("x", "y")
"""The horizontal gyros the fit takes (a sample with any gyro NaN is never placed, as in place_samples)."""


class MotionFeed:
    """A MotionFitAccumulator with what the result needs besides the fit: the first sample index of
    the stream, the dwells seen, and the reason it stopped if a call refused (the fit is then not
    available, with that reason, live and in replay alike)."""

    def __init__(self, rate_hz: float, first_index: int | None) -> None:
        self.rate_hz = float(rate_hz)
        self.accumulator = MotionFitAccumulator(self.rate_hz, AXES, RUN_TERMS)
        self.first_index = first_index
        self.dwells: list[tuple[int, int, float]] = []
        self.returned = False
        self.why_not: str | None = None

    def add_samples(self, sample_index: np.ndarray, gyro_rad_s: np.ndarray) -> None:
        if self.why_not is not None or len(sample_index) == 0:
            return
        try:
            self.accumulator.add_samples(sample_index, np.asarray(gyro_rad_s, dtype=float) / DPH)
        except InputError as exc:
            self.why_not = str(exc)

    def add_dwell_event(self, event: dict[str, Any]) -> None:
        """Close the rest a `position` or `returned` event names (others are ignored)."""
        if event.get("event") not in DWELL_EVENTS or self.why_not is not None:
            return
        dwell = (int(event["imu"]["first_index"]), int(event["imu"]["last_index"]),
                 float(event["table_angle_deg"]))
        self.returned = self.returned or event["event"] == "returned"
        self.dwells.append(dwell)
        try:
            self.accumulator.add_dwell(*dwell)
        except InputError as exc:
            self.why_not = str(exc)

    def finish(self) -> None:
        """Everything handed over has been added (live: the worker has caught up)."""

    def counts(self) -> dict[str, Any]:
        """The span counts the result reports next to the fit's own (as find_motion.motion_samples)."""
        first = min(d[0] for d in self.dwells)
        return {"fit_span_device_s": float(max(d[1] for d in self.dwells) - first + 1) / self.rate_hz,
                "before_first_dwell_s": float(first - (self.first_index or 0)) / self.rate_hz,
                "through_return": self.returned}


class LiveMotionFeed(MotionFeed):
    """Live: at each dwell event the IMU's tap is drained (the sequencer has read the dwell's samples
    by then, so they were decoded) and the dwell closed — on a worker thread, in event order, so
    that the next move is commanded without waiting for the fold (at 50× the ~20–60 ms it takes on
    a loaded host would be 1–3 device seconds more between dwells). `finish` waits for it."""

    def __init__(self, imu: InertialStream) -> None:
        super().__init__(float(imu.rate_hz), imu.first_sample_index)
        self.imu = imu
        if not imu.has_gyro_z():
            self.why_not = "no gyro z: the table angle between dwells is unknown"
        self._events: queue.Queue[dict[str, Any] | None] = queue.Queue()
        self._worker: threading.Thread | None = None

    def on_event(self, event: dict[str, Any]) -> None:
        if event.get("event") not in DWELL_EVENTS:
            return
        if self._worker is None:
            self._worker = threading.Thread(target=self._work, name="motion-feed", daemon=True)
            self._worker.start()
        self._events.put(event)

    def _work(self) -> None:
        while (event := self._events.get()) is not None:
            try:
                block = self.imu.take_tapped()
                if block is not None:
                    self.add_samples(block.sample_index, block.gyro_rad_s)
                self.add_dwell_event(event)
            except Exception as exc:  # noqa: BLE001 - the fit is then unavailable, saying why
                self.why_not = self.why_not or f"motion samples: {exc}"

    def finish(self) -> None:
        if self._worker is not None:
            self._events.put(None)
            self._worker.join()
            self._worker = None


def start_live_feed(imu: InertialStream) -> LiveMotionFeed | None:
    """A live feed on `imu` if its model can tap its stream, else None (the result then decodes imu.raw)."""
    return LiveMotionFeed(imu) if imu.start_tap() else None


def replay_feed(block: ImuBlock, events: Sequence[dict[str, Any]], rate_hz: float) -> MotionFeed:
    """The same feed from a decoded session: the samples up to each dwell's end pushed in chunks
    before that dwell's event, as they had arrived live."""
    feed = MotionFeed(rate_hz, int(block.sample_index[0]) if len(block.sample_index) else None)
    gyro = np.asarray(block.gyro_rad_s, dtype=float)
    if gyro.size == 0 or not np.any(np.isfinite(gyro[:, 2])):
        feed.why_not = "no gyro z: the table angle between dwells is unknown"
        return feed
    idx = np.asarray(block.sample_index)
    pushed = 0
    for ev in events:
        if ev.get("event") not in DWELL_EVENTS:
            continue
        upto = int(np.searchsorted(idx, int(ev["imu"]["last_index"]), side="right"))
        for lo in range(pushed, upto, REPLAY_CHUNK):
            hi = min(lo + REPLAY_CHUNK, upto)
            feed.add_samples(idx[lo:hi], gyro[lo:hi])
        pushed = max(pushed, upto)
        feed.add_dwell_event(ev)
    return feed


def feed_fit_result(feed: MotionFeed, events: Sequence[dict[str, Any]], sol: Any,
                    height_m: float = 0.0) -> dict[str, Any]:
    """find_motion.motion_fit_result's dict from a feed (the same keys; live and replay alike)."""
    from northfinder.runs.find_motion import gyro_fit_summary

    feed.finish()
    if sum(e.get("event") == "start" for e in events) != 1:
        return {"available": False, "reason": "a resumed run: its sessions' sample counters do not join"}
    if sum(e.get("event") == "position" for e in events) < 3:
        return {"available": False, "reason": "fewer than 3 positions"}
    if feed.why_not is not None:
        return {"available": False, "reason": feed.why_not}
    try:
        fit, counts = feed.accumulator.fit_screened()
    except InputError as exc:
        return {"available": False, "reason": str(exc)}
    samples = {"rest": counts["rest"], "motion": counts["motion_kept"],
               "stretches_dropped": counts["stretches_dropped"], **feed.counts(),
               "stretches_disturbed": counts["stretches_disturbed"],
               "used_device_s": float(counts["samples_used"]) / feed.rate_hz}
    return gyro_fit_summary(fit, AXES, sol, height_m, samples)


class FedEventLog:
    """The run directory as the sequencer sees it (it only appends events), each event also shown
    to the live feed once it is logged."""

    def __init__(self, rundir: Any, feed: LiveMotionFeed) -> None:
        self.rundir, self.feed = rundir, feed

    def log_event(self, event: dict[str, Any]) -> None:
        self.rundir.log_event(event)
        self.feed.on_event(event)
