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

import errno
import logging
import os
import termios
import tty
from dataclasses import dataclass
from typing import Any

import can

from firmware_sim.devices.base import Device

log = logging.getLogger(__name__)
raw_log = logging.getLogger(__name__ + ".raw")  # the one place raw pty traffic is logged

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
MAX_PENDING_BYTES = 256 * 1024  # adapter's transmit buffer toward the host; beyond it frames drop


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
    arbitration_id = int(text[1 : 1 + id_len], 16)
    if arbitration_id > (0x1FFFFFFF if extended else 0x7FF):
        raise ValueError(f"slcan frame ID out of range: {text!r}")
    dlc = int(text[1 + id_len])
    if dlc > 8:
        raise ValueError(f"slcan DLC above 8: {text!r}")
    payload = text[2 + id_len :]
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


# ---------------------------------------------------------------------------------------------
# pty
# ---------------------------------------------------------------------------------------------
def open_raw_pty() -> tuple[int, int, str]:
    """A pty pair in raw mode: (non-blocking master fd, slave fd kept open, slave path).

    The slave fd stays open in this process so the master never sees EIO/hang-up while no client
    is attached (or between two clients).
    """
    master_fd, slave_fd = os.openpty()
    tty.setraw(slave_fd, termios.TCSANOW)
    os.set_blocking(master_fd, False)
    return master_fd, slave_fd, os.ttyname(slave_fd)


@dataclass
class AdapterStats:
    """Traffic through the adapter, both ways."""

    to_client: int = 0  # frames written toward the client
    from_client: int = 0  # frames the client put onto the bus
    dropped_closed: int = 0  # bus frames dropped because the channel was closed
    overruns: int = 0  # bus frames dropped because the client did not read fast enough
    errors: int = 0  # commands answered with BEL


class SlcanAdapter(Device):
    """A Lawicel/slcan adapter: a raw pty on one side, `internal_bus` on the other."""

    name = "can"

    def __init__(self, internal_bus: can.BusABC) -> None:
        self.bus = internal_bus
        self.master_fd, self._slave_fd, self.slave_path = open_raw_pty()
        self.bitrate: int | None = None
        self.is_open = False
        self.listen_only = False
        self.stats = AdapterStats()
        self._rx = bytearray()  # bytes from the client, up to an incomplete line
        self._tx = bytearray()  # bytes owed to the client
        self._closed = False

    # -- Device surface --------------------------------------------------------------------
    def fileno(self) -> int | None:
        return None if self._closed else self.master_fd

    def endpoint(self) -> dict[str, Any]:
        return {"interface": "slcan", "channel": self.slave_path}

    def on_readable(self, t_device_s: float) -> None:
        """Read what the client typed, answer each command, put its frames onto the bus."""
        if self._closed:
            return
        while True:
            try:
                chunk = os.read(self.master_fd, 65536)
            except BlockingIOError:
                break
            except OSError as exc:
                if exc.errno == errno.EIO:  # no slave open: nothing to read
                    break
                raise
            if not chunk:
                break
            raw_log.debug("rx %r", chunk)
            self._rx.extend(chunk)
        self._handle_lines()
        self._flush()

    def advance(self, t_device_s: float) -> None:
        """Forward every frame waiting on the internal bus (if open), then write what is owed."""
        if self._closed:
            return
        while (msg := self.bus.recv(timeout=0)) is not None:
            if msg.is_error_frame or msg.is_fd:
                continue
            if not self.is_open:
                self.stats.dropped_closed += 1
                continue
            if len(self._tx) > MAX_PENDING_BYTES:
                self.stats.overruns += 1
                continue
            self._tx += encode_frame(msg)
            self.stats.to_client += 1
        self._flush()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for fd in (self.master_fd, self._slave_fd):
            try:
                os.close(fd)
            except OSError:
                pass

    # -- protocol ------------------------------------------------------------------------------
    def _handle_lines(self) -> None:
        while True:
            end = self._rx.find(b"\r")
            if end < 0:
                break
            line = bytes(self._rx[:end]).replace(b"\n", b"")
            del self._rx[: end + 1]
            reply = self.command(line)
            if reply:
                self._tx += reply
        if len(self._rx) > 4096:  # garbage without a CR: a real adapter's line buffer overflows
            self._rx.clear()
            self._tx += BELL
            self.stats.errors += 1

    def command(self, line: bytes) -> bytes:
        """Act on one line from the client (without its `\\r`); return the reply bytes."""
        if not line:
            return b""
        head = line[:1]
        if head in b"tTrR" and len(head) == 1:
            return self._client_frame(line)
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

    def _client_frame(self, line: bytes) -> bytes:
        if not self.is_open or self.listen_only:
            return self._error()
        try:
            msg = decode_frame(line)
        except ValueError:
            return self._error()
        self.bus.send(msg)
        self.stats.from_client += 1
        return b"Z\r" if msg.is_extended_id else b"z\r"

    def _error(self) -> bytes:
        self.stats.errors += 1
        return BELL

    def _flush(self) -> None:
        """Write as much of what is owed as the pty takes now; the rest waits for the next call."""
        if not self._tx:
            return
        try:
            n = os.write(self.master_fd, self._tx)
        except BlockingIOError:
            return
        except OSError as exc:
            if exc.errno == errno.EIO:
                return
            raise
        if raw_log.isEnabledFor(logging.DEBUG):
            raw_log.debug("tx %r", bytes(self._tx[:n]))
        del self._tx[:n]
