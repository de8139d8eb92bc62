"""The CAN bus inside firmware_sim between the node and the emulated slcan adapter.

Two python-can buses (`BusABC`) joined back to back: what one end sends, the other receives, in
order, as the very message object sent (the senders build a new `can.Message` for every frame and
never touch it again). python-can's `virtual` bus deep-copies every frame for every receiver —
~20 % of the simulator's CPU at 100× with 90 accelerometer frames per device second — and stamps it
with the wall clock, which nothing behind the adapter reads. The client's side of the adapter is
unchanged: a pty speaking slcan to python-can's own client.
"""

from __future__ import annotations

from collections import deque

import can


class WireEnd(can.BusABC):
    """One end of a :func:`wire`: `send` queues the frame for the other end, `recv` takes what the
    other end sent (never blocking: the simulator's loop polls with `timeout=0`)."""

    def __init__(self, channel: str, inbox: deque[can.Message], outbox: deque[can.Message]) -> None:
        self.channel_info = channel
        self._inbox = inbox
        self._outbox = outbox
        self._open = True
        super().__init__(channel=channel)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if not self._open:
            raise can.CanOperationError("the wire end is shut down")
        self._outbox.append(msg)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        try:
            return self._inbox.popleft(), False
        except IndexError:
            return None, False

    def shutdown(self) -> None:
        self._open = False
        super().shutdown()


def arrival_s(bus: can.BusABC, msg: can.Message, earliest_s: float, now_s: float) -> float:
    """The device time a frame received on `bus` came in, within [earliest_s, now_s] (the last
    frame's time and the tick's): on a :func:`wire` its `timestamp`, which the slcan adapter set to
    the device time the frame's line arrived (SlcanAdapter.on_input), so that a node acts on a
    command when it came in, as a real one does, not at the tick that hands it on (up to 0.1 device
    s later at 120×, so that an NMT stop could take effect after a move command sent after it). On any
    other bus (virtual, socketcan: wall-clock stamps) `now_s`."""
    if isinstance(bus, WireEnd):
        return min(max(float(msg.timestamp), earliest_s), now_s)
    return now_s


def wire(channel: str) -> tuple[WireEnd, WireEnd]:
    """Two bus ends joined back to back: (the node's, the adapter's)."""
    a_to_b: deque[can.Message] = deque()
    b_to_a: deque[can.Message] = deque()
    return WireEnd(channel, b_to_a, a_to_b), WireEnd(channel, a_to_b, b_to_a)
