"""The find's per-sample fit fed as the run goes (runs/find_motion_feed.py; issue 27 items 4, 5).

Live, the fit takes the IMU's tap (every decoded sample, read by the sequencer or not) at each dwell
event; replay pushes the decoded imu.raw in chunks. Checked here: the tap gives exactly what a decode
of the raw bytes gives (the driver on a scripted transport, bytes in odd chunks, a lost stretch, a
flagged frame, the counter wrapping), and the live feed, fed in whatever pieces the reader delivered,
equals the replay feed bit for bit. The whole chain (firmware-sim, live result = replay) is
tests/test_e2e_find.py's _check_replay.
"""

from __future__ import annotations

import queue

import numpy as np

from northfinder.codecs import kvh
from northfinder.constants import DPH
from northfinder.devices.imu import ImuBlock
from northfinder.drivers.imu import Imu
from northfinder.runs import find_motion_feed as F
from tests.test_motion_accumulator import RATE_HZ, _noisy_stream


class _Chunks:
    """A byte transport that hands out the chunks it was given, one per read."""

    def __init__(self) -> None:
        self.rx: queue.Queue[bytes] = queue.Queue()

    def write(self, data: bytes) -> None:
        raise AssertionError(f"unexpected write {data!r}")

    def read_available(self, max_bytes: int = 1 << 16) -> bytes:
        try:
            return self.rx.get(timeout=0.01)
        except queue.Empty:
            return b""

    def close(self) -> None:
        pass


def _raw_stream(n: int = 600, seed: int = 3) -> bytes:
    rng = np.random.default_rng(seed)
    seq = np.arange(n) + 5
    keep = np.ones(n, dtype=bool)
    keep[200:237] = False  # 37 frames lost on the line
    status = np.full(n, 0x77, dtype=np.uint8)
    status[300] = 0x76  # one frame with the x gyro flagged not valid
    gyro = rng.normal(0.0, 1e-5, (n, 3))
    accel = rng.normal(0.0, 1e-3, (n, 3))
    return kvh.encode_frames(gyro[keep], accel[keep], status[keep], seq[keep], np.full(keep.sum(), 30))


def test_tap_gives_what_a_decode_of_the_raw_log_gives():
    raw = b"\x00\x13garbage" + _raw_stream()
    t = _Chunks()
    rng = np.random.default_rng(5)
    cuts = np.sort(rng.choice(np.arange(1, len(raw)), 40, replace=False))
    taken = []
    with Imu("chunks://kvh", transport=t, wait_for_data=False, timeout_s=10.0) as imu:
        assert imu.start_tap() and imu.first_sample_index is None
        for k, piece in enumerate(np.split(np.frombuffer(raw, np.uint8), cuts)):
            t.rx.put(piece.tobytes())
            if k % 7 == 3:
                taken.append(imu.take_tapped())
        with imu._cond:  # wait (device data, not host time) until every frame is decoded
            imu._wait_locked(lambda: imu._decoder.stats.frames == 600 - 37, 10.0, lambda: "not decoded")
        taken.append(imu.take_tapped())
        first = imu.first_sample_index
    whole, _ = kvh.decode_imu_stream(raw)
    index = np.concatenate([b.sample_index for b in taken])
    gyro = np.concatenate([b.gyro_rad_s for b in taken])
    assert first == int(whole.sample_index[0])
    assert np.array_equal(index, whole.sample_index)
    assert np.array_equal(gyro, whole.gyro_rad_s, equal_nan=True)
    assert np.isnan(gyro).any()  # the flagged frame came through as NaN, as in replay


class _FakeImu:
    """What LiveMotionFeed asks of an IMU: its rate, first index, z gyro and the tap."""

    def __init__(self, idx: np.ndarray, gyro_rad_s: np.ndarray) -> None:
        self.rate_hz, self.idx, self.gyro = RATE_HZ, idx, gyro_rad_s
        self.first_sample_index = int(idx[0])
        self.decoded = 0  # samples the reader has decoded so far
        self.tapped = 0

    def has_gyro_z(self) -> bool:
        return True

    def take_tapped(self) -> ImuBlock:
        lo, self.tapped = self.tapped, self.decoded
        n = self.decoded - lo
        return ImuBlock(sample_index=self.idx[lo:self.decoded], gyro_rad_s=self.gyro[lo:self.decoded],
                        accel_g=np.zeros((n, 3)), status=np.zeros(n, np.uint8),
                        temperature_c=np.zeros(n), lost_samples=0, rate_hz=RATE_HZ)


def _events(dwells) -> list[dict]:
    evs = [{"event": "start"}]
    for k, (a, b, e) in enumerate(dwells):
        kind = "returned" if k == len(dwells) - 1 else "position"
        evs.append({"event": kind, "table_angle_deg": e, "imu": {"first_index": a, "last_index": b}})
    return evs


def _fit_of(feed: F.MotionFeed):
    fit, counts = feed.accumulator.fit_screened()
    return fit.coefficients, fit.covariance, {k: v[0] for k, v in fit.residual_rms.items()}, counts


def test_live_feed_equals_replay_feed_bit_for_bit(monkeypatch):
    idx, gyro_dph, dwells = _noisy_stream(knock=True)
    gyro = gyro_dph * DPH
    events = _events(dwells)
    fake = _FakeImu(idx, gyro)
    live = F.LiveMotionFeed(fake)
    rng = np.random.default_rng(9)
    for ev in events[1:]:
        # the reader decodes in odd pieces, past the dwell's end, before the event is logged
        target = int(np.searchsorted(idx, ev["imu"]["last_index"], side="right")) + int(rng.integers(0, 300))
        while fake.decoded < min(target, idx.size):
            fake.decoded = min(idx.size, fake.decoded + int(rng.integers(1, 500)))
            if rng.random() < 0.3:
                piece = fake.take_tapped()  # the feed also takes what it is handed between dwells
                live.add_samples(piece.sample_index, piece.gyro_rad_s)
        live.on_event(ev)
        live.finish()  # the worker has taken this much from the tap (as the live run's reader runs on)
    assert len(live.dwells) == len(dwells) and live.why_not is None
    assert live.accumulator.counts["stretches_dropped"] == 0
    block = ImuBlock(sample_index=idx, gyro_rad_s=gyro, accel_g=np.zeros((idx.size, 3)),
                     status=np.zeros(idx.size, np.uint8), temperature_c=np.zeros(idx.size), lost_samples=0,
                     rate_hz=RATE_HZ)
    replayed = F.replay_feed(block, events, RATE_HZ)
    monkeypatch.setattr(F, "REPLAY_CHUNK", 97)
    small_chunks = F.replay_feed(block, events, RATE_HZ)
    ours = _fit_of(live)
    assert ours[3]["stretches_disturbed"] == 1  # the knock's stretch is left out
    for other in (replayed, small_chunks):
        theirs = _fit_of(other)
        assert np.array_equal(ours[0], theirs[0]) and np.array_equal(ours[1], theirs[1])
        assert ours[2] == theirs[2] and ours[3] == theirs[3]
        assert other.counts() == live.counts()
    assert live.counts()["through_return"] is True


def test_a_refused_stream_makes_the_fit_unavailable_with_its_reason():
    feed = F.MotionFeed(RATE_HZ, 0)
    feed.add_samples(np.array([5, 6]), np.zeros((2, 3)))
    feed.add_samples(np.array([6, 7]), np.zeros((2, 3)))  # an index again: the stream cannot be placed
    assert feed.why_not is not None and "increase" in feed.why_not
    events = [{"event": "start"}] + [{"event": "position"}] * 3
    assert F.feed_fit_result(feed, events, None) == {"available": False, "reason": feed.why_not}


def test_pace_note_names_the_time_scale_only_when_a_clean_simulated_link_lost_samples():
    from northfinder.runs.find import pace_note

    def events(scale, faults=(), imu_lost=0, crc=0, acc_lost=0, simulate=True):
        sim = {"time_scale": scale, "faults": list(faults)} if simulate else None
        start = {"event": "start", "simulate": sim}
        stats = {"event": "stats", "imu": {"lost_samples": imu_lost, "bad_crc": crc},
                 "accel": {"lost_samples": acc_lost}}
        return [start, stats]

    note = pace_note(events(80, imu_lost=5559, crc=74))
    assert note is not None and "--time-scale 80" in note and "5,559" in note and "74 bad CRCs" in note
    assert "accelerometer 12" in pace_note(events(50, acc_lost=12))
    assert pace_note(events(80)) is None  # lossless
    assert pace_note(events(1, imu_lost=3)) is None  # real time: the link, not the host's pace
    assert pace_note(events(80, faults=["imu-drop-byte-rate=0.001"], imu_lost=3)) is None  # asked for
    assert pace_note(events(80, imu_lost=3, simulate=False)) is None  # a real bench
