"""firmware_sim takes a client's input at the device time it arrived (firmware_sim.arrivals), not
when its loop got to it: real ptys, a clock the test sets, and the simulator itself with a tick
that sleeps. Waits are bounded generously; the assertions are on device times."""

from __future__ import annotations

import os
import select
import threading
import time

import pytest
import serial
from helpers import SerialKeepingInput

from firmware_sim.arrivals import ArrivalStamper
from firmware_sim.config import SimConfig
from firmware_sim.devices.base import Device
from firmware_sim.pty import PtyPort
from firmware_sim.simulator import Simulator

WAIT_S = 10.0


class SetClock:
    """A device clock the test moves by hand."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def wait_readable(fd: int) -> None:
    assert select.select([fd], [], [], WAIT_S)[0], "nothing was stamped"


def take_all(stamper: ArrivalStamper, n_bytes: int) -> list[tuple[float, PtyPort, bytes]]:
    """Everything stamped until `n_bytes` are in (a client's write may come in pieces)."""
    out: list[tuple[float, PtyPort, bytes]] = []
    deadline = time.monotonic() + WAIT_S
    while sum(len(d) for _, _, d in out) < n_bytes and time.monotonic() < deadline:
        wait_readable(stamper.fileno())
        out += stamper.take()[1]
    return out


@pytest.fixture
def ports():
    made = [PtyPort("a"), PtyPort("b")]
    clients = [serial.Serial(p.path, 115200, timeout=0) for p in made]
    yield made, clients
    for c in clients:
        c.close()
    for p in made:
        p.close()


def test_input_is_stamped_when_it_arrives_not_when_it_is_taken(ports) -> None:
    (a, b), (client_a, client_b) = ports
    clock = SetClock()
    stamper = ArrivalStamper(clock)
    try:
        stamper.watch({a: a, b: b})
        clock.t = 12.5
        client_a.write(b"1PA45\r\n")
        got = take_all(stamper, 7)
        clock.t = 13.0
        client_b.write(b"?DR\n")
        wait_readable(stamper.fileno())
        clock.t = 99.0  # the loop comes late: the stamps do not move
        t, arrived = stamper.take()
    finally:
        stamper.close()
    assert t == 99.0
    assert [(ts, port) for ts, port, _ in got] == [(12.5, a)] * len(got)
    assert b"".join(d for _, _, d in got) == b"1PA45\r\n"
    assert [(ts, port, data) for ts, port, data in arrived] == [(13.0, b, b"?DR\n")]


def test_a_port_is_read_only_while_it_is_watched(ports) -> None:
    (a, b), (client_a, client_b) = ports
    clock = SetClock()
    stamper = ArrivalStamper(clock)
    try:
        stamper.watch({a: a})
        client_b.write(b"early\n")
        client_a.write(b"x\n")
        assert b"".join(d for _, _, d in take_all(stamper, 2)) == b"x\n"
        assert b.read() == b"early\n"  # b was never read by the stamper: its bytes still wait
        clock.t = 3.0
        stamper.watch({a: a, b: b})
        client_b.write(b"late\n")
        arrived = take_all(stamper, 5)
    finally:
        stamper.close()
    assert [(ts, port) for ts, port, _ in arrived] == [(3.0, b)] * len(arrived)


def test_a_client_that_leaves_does_not_keep_the_thread_busy(ports) -> None:
    """A master whose client closed polls readable (hang-up) forever: the thread leaves it out."""
    (a, _), (client_a, _) = ports
    stamper = ArrivalStamper(SetClock())
    try:
        stamper.watch({a: a})
        client_a.close()
        time.sleep(0.3)
        t0 = os.times()
        time.sleep(0.5)
        t1 = os.times()
    finally:
        stamper.close()
    # this process's CPU while the stamper watched a hung-up port: far below a spinning thread's
    used_s = (t1.user - t0.user) + (t1.system - t0.system)
    assert used_s < 0.25, f"{used_s:.2f} s of CPU in 0.5 s"


class SleepyDevice(Device):
    """A device whose every tick takes `sleep_s` of wall time (the loop is busy meanwhile)."""

    name = "sleepy"

    def __init__(self, sleep_s: float) -> None:
        self.sleep_s = sleep_s
        self.asleep = threading.Event()

    def advance(self, t_device_s: float) -> None:
        self.asleep.set()
        time.sleep(self.sleep_s)
        self.asleep.clear()


def test_a_move_starts_when_its_command_arrived_while_the_loop_was_busy() -> None:
    """The SMC100's move is planned from the PA's arrival: not a tick later, when the loop (here
    asleep in a slow device for 2 s of device time) got to it."""
    scale = 20.0
    sim = Simulator(SimConfig(seed=3, time_scale=scale, accel_enabled=False))
    endpoints = sim.start()
    moves: list[dict] = []
    handled_at: list[float] = []
    sleepy = SleepyDevice(2.0 / scale)
    try:
        stage = sim.turntable
        stage.on_event = lambda kind, t, info: moves.append(info) if kind == "move" else None
        on_input = stage.on_input

        def noting(data: bytes, t: float) -> None:
            handled_at.append(sim.clock.now())
            on_input(data, t)

        stage.on_input = noting
        with SerialKeepingInput(endpoints["turntable"], 57600, timeout=WAIT_S) as client:
            client.write(b"1OR\r\n")  # home first: PA is refused while NOT REFERENCED
            deadline = time.monotonic() + WAIT_S
            while not moves and time.monotonic() < deadline:
                time.sleep(0.01)
            assert moves, "the stage did not start homing"
            sim.run_for(moves[0]["t_end_s"] - sim.now() + 0.5)  # homed: READY
            sim.devices.append(sleepy)
            assert sleepy.asleep.wait(WAIT_S)
            written_after = sim.now()
            client.write(b"1PA10\r\n")
            deadline = time.monotonic() + WAIT_S
            while len(moves) < 2 and time.monotonic() < deadline:
                time.sleep(0.01)
    finally:
        sim.stop()
    assert len(moves) == 2, f"moves planned: {moves}"
    t_start = moves[1]["t_start_s"]
    assert t_start >= written_after
    assert handled_at[-1] - t_start > 0.5, (
        f"the move was planned from {t_start:.3f} s, when the loop took it ({handled_at[-1]:.3f} s)")


def test_a_client_that_closes_and_opens_the_port_again_is_read(ports) -> None:
    """The loop may never see the port without a client (a close and an open within one tick):
    the thread looks at a hung-up port again by itself."""
    (a, _), (client_a, _) = ports
    clock = SetClock()
    stamper = ArrivalStamper(clock)
    try:
        stamper.watch({a: a})
        client_a.close()
        deadline = time.monotonic() + WAIT_S
        while a.connected and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.05)  # the thread has seen the hang-up
        with serial.Serial(a.path, 115200, timeout=0) as again:
            clock.t = 7.0
            again.write(b"0SE\r")
            arrived = take_all(stamper, 4)
    finally:
        stamper.close()
    assert b"".join(d for _, _, d in arrived) == b"0SE\r"
    assert {ts for ts, _, _ in arrived} == {7.0}


def test_what_stops_the_thread_reaches_the_loop(ports) -> None:
    """An unexpected error in the arrival thread is raised by take(), so the simulator's loop fails
    and says why instead of going deaf to every client."""
    (a, _), (client_a, _) = ports

    def broken(max_bytes: int = 65536) -> bytes:
        raise RuntimeError("concurrent poll() invocation")

    a.read = broken
    stamper = ArrivalStamper(SetClock())
    try:
        stamper.watch({a: a})
        client_a.write(b"x")
        wait_readable(stamper.fileno())
        with pytest.raises(RuntimeError, match="arrival thread stopped"):
            stamper.take()
    finally:
        stamper.close()


def test_two_threads_may_ask_whether_a_client_is_there(ports) -> None:
    """PtyPort.connected from the loop and the arrival thread at once (one poll object: CPython
    raises on a concurrent poll())."""
    (a, _), _ = ports
    errors: list[BaseException] = []

    def ask() -> None:
        try:
            for _ in range(20_000):
                assert a.connected
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=ask) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors[0]


def _stop_thread(stamper: ArrivalStamper) -> None:
    """End the stamper's thread (its pipes stay open): as if a busy host kept it off every CPU."""
    stamper._stopping = True
    os.write(stamper._ctl_w, b"\0")
    stamper._thread.join(WAIT_S)
    assert not stamper._thread.is_alive()


def test_the_loop_stamps_what_came_while_the_thread_could_not_run(ports) -> None:
    """poll(): the loop reads and stamps the input itself between its devices, so a thread that
    waits for a CPU (milliseconds on a busy 2-core host, tenths of a device second at 120×) no
    longer decides when a command took effect."""
    (a, _b), (client_a, _client_b) = ports
    clock = SetClock()
    stamper = ArrivalStamper(clock)
    try:
        stamper.watch({a: a})
        _stop_thread(stamper)
        clock.t = 3.25
        client_a.write(b"1PA45\r\n")
        got: list[tuple[float, PtyPort, bytes]] = []
        deadline = time.monotonic() + WAIT_S
        while sum(len(d) for _, _, d in got) < 7 and time.monotonic() < deadline:
            stamper.poll()
            got += stamper.take()[1]
            time.sleep(0.001)
        clock.t = 4.0
        assert stamper.take()[1] == []
    finally:
        stamper.close()
    assert [(ts, port) for ts, port, _ in got] == [(3.25, a)] * len(got)
    assert b"".join(d for _, _, d in got) == b"1PA45\r\n"


class PipePort:
    """A port whose client is a pipe (its bytes are readable the moment they are written)."""

    def __init__(self) -> None:
        self.master_fd, self.client_fd = os.pipe()
        os.set_blocking(self.master_fd, False)
        self.connected = True

    def read(self) -> bytes:
        try:
            return os.read(self.master_fd, 65536)
        except BlockingIOError:
            return b""

    def close(self) -> None:
        os.close(self.master_fd)
        os.close(self.client_fd)


class BytesDuringTheReading:
    """A device clock whose first reading lets the client's next bytes in right after it: they came
    after that device time, so no stamp of theirs may be as early."""

    def __init__(self, port: PipePort) -> None:
        self.port, self.t, self.wrote_at = port, 0.0, None

    def __call__(self) -> float:
        self.t += 1.0
        if self.wrote_at is None:
            self.wrote_at = self.t
            os.write(self.port.client_fd, b"1TP\r\n")
        return self.t


def test_bytes_that_come_while_a_chunk_is_read_are_not_stamped_before_they_came() -> None:
    """The stamp is read after the ports are: bytes that land between the clock's reading and the
    read would otherwise carry a time from before they came (an in-process client that asked for
    the table angle got one from before its question, once in a serial run of the suite)."""
    port = PipePort()
    clock = BytesDuringTheReading(port)
    stamper = ArrivalStamper(clock)
    try:
        _stop_thread(stamper)
        stamper.watch({port: port})
        os.write(port.client_fd, b"1TS\r\n")
        got: list[tuple[float, PipePort, bytes]] = []
        deadline = time.monotonic() + WAIT_S
        while sum(len(d) for _, _, d in got) < 10 and time.monotonic() < deadline:
            stamper.poll()
            got += stamper.take()[1]
    finally:
        stamper.close()
        port.close()
    assert b"".join(d for _, _, d in got) == b"1TS\r\n1TP\r\n"
    assert clock.wrote_at is not None
    late = [t for t, _, d in got if b"TP" in d]
    assert late and min(late) > clock.wrote_at
