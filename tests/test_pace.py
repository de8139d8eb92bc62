"""`find --time-scale auto` (runs.find_pace), the position event's `before_move_s`, firmware-sim's
`--control-stdin` and the device clock's continuous change of scale.

The pace's rule is tested on events (pure); the end-to-end run checks that every change of scale it
logged follows that rule from the run's own events — which scales a host reaches depends on the host,
so no test names them.
"""

from __future__ import annotations

import gc
import json
import subprocess
import sys

import pytest
from helpers import read_events, run_cli, subprocess_env

from firmware_sim import clock as sim_clock
from northfinder.runs import find_pace as P
from northfinder.runs.base import heap_frozen
from northfinder.runs.find import pace_note


def _position(index, before_move_s, imu_lost=0, accel_lost=0):
    return {"event": "position", "index": index, "before_move_s": before_move_s,
            "imu": {"lost": imu_lost}, "accel": {"lost": accel_lost}}


def test_the_pace_doubles_with_room_halves_when_behind_and_stays_in_its_bounds():
    asked, logged = [], []
    pace = P.AutoPace(asked.append, logged.append, start_scale=40.0, max_scale=160.0)
    assert asked == [40.0] and logged[0]["why"] == "start"
    pace.on_event(_position(0, None))  # the first position has no dwell before it: no change
    assert pace.scale == 40.0
    pace.on_event(_position(1, P.ROOM_S))  # room to spare
    pace.on_event(_position(2, P.ROOM_S / 2))
    assert asked[-2:] == [80.0, 160.0]
    pace.on_event(_position(3, 0.0))  # at the maximum already
    assert pace.scale == 160.0 and len(asked) == 3
    pace.on_event(_position(4, (P.ROOM_S + P.KEEP_UP_S) / 2))  # keeps up, no room: stays
    assert pace.scale == 160.0
    pace.on_event(_position(5, P.KEEP_UP_S * 1.01))
    assert pace.scale == 80.0
    pace.on_event(_position(6, 0.0, accel_lost=3))  # a link lost samples: behind, whatever the lag
    assert pace.scale == 40.0
    pace.on_event({"event": "remeasure", "index": 6, "attempt": 1, "reason": "imu lost 9 of 100"})
    assert pace.scale == 20.0
    for _ in range(10):
        pace.on_event(_position(7, 10.0))
    assert pace.scale == P.AUTO_MIN_SCALE
    assert [e["scale"] for e in logged] == [40.0, 80.0, 160.0, 80.0, 40.0, 20.0, 10.0, 5.0, 2.5, 1.25, 1.0]


def test_with_faults_injected_the_lag_alone_paces():
    asked = []
    pace = P.AutoPace(asked.append, lambda _e: None, start_scale=40.0, losses_count=False)
    pace.on_event(_position(1, P.ROOM_S, imu_lost=50))  # the fault's loss, not the host's
    pace.on_event({"event": "remeasure", "index": 1, "attempt": 1, "reason": "imu lost 50 of 1000"})
    assert pace.scale == 80.0
    pace.on_event(_position(2, 2 * P.KEEP_UP_S))
    assert pace.scale == 40.0


def test_pace_note_says_when_device_time_ran_on_between_dwells():
    start = {"event": "start", "simulate": {"time_scale": 120.0, "faults": []}}
    stats = {"event": "stats", "imu": {"lost_samples": 0, "bad_crc": 0}, "accel": {"lost_samples": 0}}
    slow = [start, _position(0, None), *(_position(i, 3.0 * P.KEEP_UP_S) for i in range(1, 4)), stats]
    note = pace_note(slow)
    assert note is not None and "--time-scale 120" in note
    assert "between a dwell's end and the next move" in note
    quick = [start, *(_position(i, P.KEEP_UP_S / 2) for i in range(1, 4)), stats]
    assert pace_note(quick) is None
    once = [start, _position(1, P.KEEP_UP_S / 2), _position(2, 7.4), _position(3, P.KEEP_UP_S / 2), stats]
    note = pace_note(once)  # the median kept up, one move did not
    assert note is not None and "fell behind at 1 of 3 moves" in note and "up to 7.4 s" in note
    paced = [{**start, "simulate": {"time_scale": "auto", "faults": []}},
             {"event": "time_scale", "scale": 40.0}, {"event": "time_scale", "scale": 80.0}, *slow[1:]]
    assert "--time-scale 80 (auto)" in pace_note(paced)
    assert P.pace_line(paced) == "time scale auto: 40 → 80×"


def test_the_device_clock_changes_scale_without_a_jump(monkeypatch):
    wall = [100.0]
    monkeypatch.setattr(sim_clock.time, "monotonic", lambda: wall[0])
    c = sim_clock.DeviceClock(10.0)
    c.start()
    wall[0] += 2.0
    assert c.now() == pytest.approx(20.0)
    c.set_scale(100.0)
    assert c.now() == pytest.approx(20.0) and c.time_scale == 100.0
    wall[0] += 0.5
    assert c.now() == pytest.approx(70.0)
    assert c.wall_s(50.0) == pytest.approx(0.5)
    with pytest.raises(ValueError):
        c.set_scale(0.0)


def test_control_stdin_refuses_a_bad_line_by_name_and_ends_with_its_input():
    proc = subprocess.Popen([sys.executable, "-m", "firmware_sim", "--time-scale", "10", "--control-stdin"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=subprocess_env())
    try:
        endpoints = json.loads(proc.stdout.readline())
        assert "turntable" in endpoints
        proc.stdin.write("time-scale 25\ntime-scale 0\nwarp 9\n")
        proc.stdin.close()  # its client has gone: the simulator ends
        assert proc.wait(timeout=30) == 0
        err = proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert "unknown control line 'time-scale 0'" in err and "unknown control line 'warp 9'" in err
    assert "'time-scale 25'" not in err


@pytest.mark.slow
def test_find_time_scale_auto_paces_by_its_own_events_and_replays(tmp_path):
    out = tmp_path / "run"
    found = run_cli("find", "--simulate", "--positions", "4", "--dwell", "3", "--time-scale", "auto",
                    "--out", str(out), "--no-report", "--db", str(tmp_path / "h.db"), cwd=tmp_path,
                    timeout_s=240)
    assert found.returncode == 0, found.stderr
    assert "time scale auto: 40" in found.stderr
    events = read_events(out)
    start = next(e for e in events if e["event"] == "start")
    assert start["simulate"]["time_scale"] == "auto"
    logged = [e for e in events if e["event"] == "time_scale"]
    assert logged[0] == {"event": "time_scale", "scale": P.AUTO_START_SCALE, "why": "start"}
    # the rule, run again on the run's own positions and re-measures, logs the same changes
    again: list[dict] = []
    pace = P.AutoPace(lambda _k: None, again.append)
    for e in events:
        pace.on_event(e)
    assert again == logged
    positions = [e for e in events if e["event"] == "position"]
    assert len(positions) == 4 and positions[0]["before_move_s"] is None
    assert all(p["before_move_s"] > 0 for p in positions[1:])
    replayed = run_cli("replay", str(out), cwd=tmp_path)
    assert replayed.returncode == 0, replayed.stderr
    assert "identical" in replayed.stdout


def _counting_collections(monkeypatch) -> list[int]:
    """gc.collect still collects, and each call is appended to the list returned."""
    collections: list[int] = []
    collect = gc.collect
    monkeypatch.setattr(gc, "collect", lambda *a: collections.append(1) or collect(*a))
    return collections


def test_heap_frozen_freezes_what_is_there_and_unfreezes_after_a_failure_too(monkeypatch):
    """What lives before the body is out of the collector's reach in it (a full collection would
    stop the run's threads); afterwards everything is collectable again, however the body ended.
    It does not collect first: by then the devices stream (prepare_to_stream does)."""
    collections = _counting_collections(monkeypatch)
    gc.unfreeze()
    held = [[k] for k in range(5000)]  # containers: tracked by the collector
    with pytest.raises(RuntimeError), heap_frozen():
        assert gc.get_freeze_count() >= len(held)
        raise RuntimeError("the body failed")
    assert gc.get_freeze_count() == 0
    assert not collections


def _before_the_first_open(monkeypatch, start) -> tuple[set[str], int]:
    """Run `start()` until it opens its first device (registry.open_device, stopped there): the roles
    whose model module was loaded by then, and how many full collections ran before it."""
    from northfinder.devices import registry

    seen: list[set[str]] = []

    def first_open(role, *args, **kwargs):
        seen.append({key.split("/")[0] for key in registry._loaded})
        raise RuntimeError("stop at the first open")

    collections = _counting_collections(monkeypatch)
    monkeypatch.setattr(registry, "_loaded", {})
    monkeypatch.setattr(registry, "open_device", first_open)
    with pytest.raises(RuntimeError, match="first open"):
        start()
    return seen[0], len(collections)


def test_find_imports_every_device_model_and_collects_before_it_opens_the_first_device(monkeypatch):
    """A module imported, or a full collection, while the IMU streams holds the interpreter for tens
    of ms (the CAN accelerometer's modules: canopen, cantools; a collection: 64 ms) and the IMU
    reader falls behind by that times the time scale; so open_bench does both first."""
    from northfinder.config import BenchConfig
    from northfinder.runs.find import open_bench

    def start():
        with open_bench(BenchConfig(source="test"), None):
            pass

    roles, collections = _before_the_first_open(monkeypatch, start)
    assert roles == {"turntable", "imu", "accelerometer"}
    assert collections, "the heap is collected before the devices stream (heap_frozen does not)"


def test_the_find_command_imports_its_live_view_with_the_command():
    """rich.progress takes ~50 ms to import: not when the view opens, its devices streaming."""
    code = "import sys, northfinder.cli.find; print('rich.progress' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=subprocess_env(),
                         timeout=60, check=True)
    assert out.stdout.strip() == "True"


def test_align_gnss_imports_both_models_and_collects_before_it_opens_the_imu(tmp_path, monkeypatch):
    """The receiver's model (pynmeagps) was imported once the IMU streamed: the same start-up stall,
    here in the host stamps the IMU–GNSS coarse offset comes from (runs.base.prepare_to_stream)."""
    from northfinder.config import GnssConfig, ImuConfig
    from northfinder.rundir import RunDir
    from northfinder.runs import gnss_live

    roles, collections = _before_the_first_open(monkeypatch, lambda: gnss_live.acquire(
        RunDir(tmp_path / "run"), imu=ImuConfig(port="loop://"), gnss=GnssConfig(port="loop://"),
        duration_s=1.0, filter_settings={}))
    assert roles == {"imu", "gnss"}
    assert collections
