"""slcan (Lawicel ASCII) USB-CAN adapter on a pseudo-terminal (docs/PROTOCOLS.md §4).

Bridges the simulator's internal python-can bus to a client in another process that opens the
pty slave with python-can's own `slcan` interface. Like a cheap adapter: `S0`…`S8` set the
bitrate, `O`/`L` open (normal / listen-only), `C` closes, `V`/`N` report version and serial
number; frames typed by the client go onto the bus; frames from the bus go to the client only
while the channel is open (dropped when closed, and counted as overruns when the client does not
read fast enough).

Leniency, on purpose: `O`/`L` on an open channel and `C` on a closed one answer OK (python-can
sends `O` twice and `C` first); an empty line (python-can's empty data-bitrate code) gets no reply.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import can

from firmware_sim.devices.base import Device
from firmware_sim.pty import PtyPort

log = logging.getLogger(__name__)

OK = b"\r"
BELL = b"\x07"
VERSION_REPLY = b"V1013\r"
SERIAL_REPLY = b"NA123\r"
BITRATES = {
    "S0": 10_000,
    "S1": 20_000,
    "S2": 50_000,
    "S3": 100_000,
    "S4": 125_000,
    "S5": 250_000,
    "S6": 500_000,
    "S7": 750_000,
    "S8": 1_000_000,
}
TX_BACKLOG_BYTES = 256 * 1024  # adapter's buffer toward the host (≈ 12 000 TPDO lines); then frames drop


# ---------------------------------------------------------------------------------------------
# Codec: one slcan line <-> one frame, pure
# ---------------------------------------------------------------------------------------------
def encode_frame(msg: can.Message) -> bytes:
    """A CAN frame as one slcan line: `tIIIL…\\r`, `TIIIIIIIIL…\\r`, `rIIIL\\r`, `RIIIIIIIIL\\r`."""
    if msg.is_extended_id:
        head = f"{'R' if msg.is_remote_frame else 'T'}{msg.arbitration_id:08X}{msg.dlc:d}"
    else:
        head = f"{'r' if msg.is_remote_frame else 't'}{msg.arbitration_id:03X}{msg.dlc:d}"
    body = "" if msg.is_remote_frame else bytes(msg.data[: msg.dlc]).hex().upper()
    return (head + body).encode("ascii") + b"\r"


_HEX = frozenset("0123456789ABCDEFabcdef")


def decode_frame(line: bytes) -> can.Message:
    """One slcan frame line (without or with its `\\r`) -> can.Message; ValueError if malformed."""
    text = line.rstrip(b"\r").decode("ascii")
    if not text or text[0] not in "tTrR":
        raise ValueError(f"not an slcan frame line: {text!r}")
    extended = text[0] in "TR"
    remote = text[0] in "rR"
    id_len = 8 if extended else 3
    if len(text) < 1 + id_len + 1:
        raise ValueError(f"slcan frame line too short: {text!r}")
    id_text, dlc_text, payload = text[1 : 1 + id_len], text[1 + id_len], text[2 + id_len :]
    # int(x, 16) alone would accept '-', '+', '0x', '_' and spaces: only hex digits are slcan
    if not all(c in _HEX for c in id_text + payload) or not dlc_text.isdigit():
        raise ValueError(f"slcan frame line with a non-hex character: {text!r}")
    arbitration_id = int(id_text, 16)
    if arbitration_id > (0x1FFFFFFF if extended else 0x7FF):
        raise ValueError(f"slcan frame ID out of range: {text!r}")
    dlc = int(dlc_text)
    if dlc > 8:
        raise ValueError(f"slcan DLC above 8: {text!r}")
    if remote:
        if payload:
            raise ValueError(f"slcan remote frame with data: {text!r}")
        data = b""
    else:
        if len(payload) != 2 * dlc:
            raise ValueError(f"slcan data length does not match DLC {dlc}: {text!r}")
        data = bytes.fromhex(payload)
    return can.Message(
        arbitration_id=arbitration_id,
        is_extended_id=extended,
        is_remote_frame=remote,
        dlc=dlc,
        data=data,
    )


@dataclass
class AdapterStats:
    """Traffic through the adapter, both ways."""

    to_client: int = 0  # frames written toward the client
    from_client: int = 0  # frames the client put onto the bus
    dropped_closed: int = 0  # bus frames dropped because the channel was closed
    overruns: int = 0  # bus frames dropped because the client did not read fast enough
    errors: int = 0  # commands answered with BEL
    wrong_bitrate: int = 0  # frames lost because the channel was opened at another bit rate


class SlcanAdapter(Device):
    """A Lawicel/slcan adapter: a raw pty (firmware_sim.pty, which logs the raw bytes) on one side,
    `internal_bus` on the other."""

    name = "can"

    def __init__(
        self,
        internal_bus: can.BusABC,
        *,
        bus_bitrate: int | None = None,
        backlog_bytes: int = TX_BACKLOG_BYTES,
    ) -> None:
        """`bus_bitrate`: the bit rate of the emulated bus; if given, a channel opened at another
        rate passes no frames either way (as on a real bus, where the adapter sees only errors)."""
        self.bus = internal_bus
        self.bus_bitrate = bus_bitrate
        self.port = PtyPort("slcan", backlog_bytes=backlog_bytes)
        self.bitrate: int | None = None
        self.is_open = False
        self.listen_only = False
        self.stats = AdapterStats()
        self._rx = bytearray()  # bytes from the client, up to an incomplete line
        self._closed = False

    @property
    def slave_path(self) -> str:
        return self.port.path

    # -- Device surface --------------------------------------------------------------------
    def input_port(self) -> PtyPort | None:
        """The pty while a client has it open; None otherwise, because a master without a client
        polls readable (hang-up) all the time and would spin the loop."""
        return None if self._closed or self.port.watch_fileno() is None else self.port

    def endpoint(self) -> dict[str, Any]:
        return {"interface": "slcan", "channel": self.port.path}

    def on_input(self, data: bytes, t_device_s: float) -> None:
        """What the client typed: answer each command, put its frames onto the bus."""
        if self._closed:
            return
        self._rx.extend(data)
        reply = self._handle_lines(t_device_s)
        if reply:
            self.port.write(reply)

    def advance(self, t_device_s: float) -> None:
        """Forward every frame waiting on the internal bus (if open), then write what is owed."""
        if self._closed:
            return
        if self.is_open and not self.port.connected:
            # the client went away without `C`: nobody reads the channel; close it so that stale
            # frames do not greet the next client
            self.is_open = False
        out = bytearray()
        room = self.port.backlog_bytes - self.port.pending
        while (msg := self.bus.recv(timeout=0)) is not None:
            if msg.is_error_frame or msg.is_fd:
                continue
            if not self.is_open:
                self.stats.dropped_closed += 1
                continue
            if self._wrong_bitrate:
                self.stats.wrong_bitrate += 1
                continue
            line = encode_frame(msg)
            if len(out) + len(line) > room:  # drop whole frames, never half a line
                self.stats.overruns += 1
                continue
            out += line
            self.stats.to_client += 1
        if out:
            self.port.write(bytes(out))
        else:
            self.port.flush()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.port.close()

    # -- protocol ------------------------------------------------------------------------------
    def _handle_lines(self, t_device_s: float) -> bytes:
        replies = bytearray()
        while True:
            end = self._rx.find(b"\r")
            if end < 0:
                break
            line = bytes(self._rx[:end]).replace(b"\n", b"")
            del self._rx[: end + 1]
            replies += self.command(line, t_device_s)
        if len(self._rx) > 4096:  # garbage without a CR: a real adapter's line buffer overflows
            self._rx.clear()
            replies += self._error()
        return bytes(replies)

    def command(self, line: bytes, t_device_s: float = 0.0) -> bytes:
        """Act on one line from the client (without its `\\r`) that arrived at `t_device_s`; return
        the reply bytes. A frame goes onto the bus stamped with that time (can_wire.arrival_s)."""
        if not line:
            return b""
        if line[:1] in (b"t", b"T", b"r", b"R"):
            return self._client_frame(line, t_device_s)
        text = line.decode("ascii", errors="replace")
        if text in BITRATES:
            if self.is_open:  # Lawicel: bitrate only on a closed channel
                return self._error()
            self.bitrate = BITRATES[text]
            return OK
        if text in ("O", "L"):
            self.is_open = True
            self.listen_only = text == "L"
            return OK
        if text == "C":
            self.is_open = False
            return OK
        if text == "V":
            return VERSION_REPLY
        if text == "N":
            return SERIAL_REPLY
        return self._error()

    def _client_frame(self, line: bytes, t_device_s: float) -> bytes:
        if not self.is_open or self.listen_only:
            return self._error()
        try:
            msg = decode_frame(line)
        except ValueError:
            return self._error()
        if self._wrong_bitrate:  # the frame never gets an ACK on a bus at another rate
            self.stats.wrong_bitrate += 1
        else:
            msg.timestamp = t_device_s
            self.bus.send(msg)
            self.stats.from_client += 1
        return b"Z\r" if msg.is_extended_id else b"z\r"

    @property
    def _wrong_bitrate(self) -> bool:
        return self.bus_bitrate is not None and self.bitrate is not None and self.bitrate != self.bus_bitrate

    def _error(self) -> bytes:
        self.stats.errors += 1
        return BELL
