"""CANopen-style accelerometer node (docs/PROTOCOLS.md §3): frames ⇄ values, no I/O.

The frames are described by ``northfinder/data/accelerometer.dbc`` (IDs for node 0x10) and
decoded with cantools; another node ID uses the same bases (0x080, 0x180, 0x280, 0x700) plus
its ID, so a frame is looked up in the DBC by ``id - node_id + 0x10``.

:class:`AccelFrameDecoder` is the stateful part shared by the live driver and the replay
path: it pairs each TPDO2 with the TPDO1 just before it, unwraps the 8-bit counter, counts
unpaired frames, counter gaps and lost samples, and keeps heartbeats and emergencies.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path

import cantools
import numpy as np

__all__ = [
    "DBC_NODE_ID",
    "DEFAULT_DBC_PATH",
    "EMCY_MEANINGS",
    "HEARTBEAT_STATES",
    "NMT_COMMANDS",
    "AccelFrameDecoder",
    "AccelStats",
    "CanCodec",
    "Emcy",
    "RawAccelSamples",
    "load_database",
]

DEFAULT_DBC_PATH = Path(__file__).resolve().parent.parent / "data" / "accelerometer.dbc"
DBC_NODE_ID = 0x10  # the node the DBC's frame IDs are written for

NMT_ID = 0x000
EMCY_BASE, TPDO1_BASE, TPDO2_BASE, HEARTBEAT_BASE = 0x080, 0x180, 0x280, 0x700

NMT_COMMANDS = {"start": 0x01, "stop": 0x02, "pre-operational": 0x80, "reset": 0x81}
HEARTBEAT_STATES = {0x00: "boot-up", 0x04: "stopped", 0x05: "operational", 0x7F: "pre-operational"}
EMCY_MEANINGS = {
    0x0000: "reset / no error",
    0x5000: "device hardware",
    0x8110: "CAN overrun",
    0x8130: "heartbeat / life guard",
}
COUNTER_MODULO = 256


@functools.lru_cache(maxsize=8)
def _load(path: str) -> cantools.database.can.Database:
    return cantools.database.load_file(path)


def load_database(path: str | Path | None = None) -> cantools.database.can.Database:
    """The project's DBC (or `path`), parsed once and cached."""
    return _load(str(Path(path) if path is not None else DEFAULT_DBC_PATH))


@dataclass(frozen=True)
class Emcy:
    """One emergency frame: error code, error register, its meaning and the vendor bytes."""

    code: int
    register: int
    meaning: str
    vendor: bytes = b""
    timestamp: float | None = None


class CanCodec:
    """Encode and decode the node's frames through the DBC, for any node ID 1–127."""

    def __init__(self, node_id: int = DBC_NODE_ID, dbc_path: str | Path | None = None) -> None:
        if not 1 <= int(node_id) <= 127:
            raise ValueError(f"CANopen node ID must be 1..127, got {node_id}")
        self.node_id = int(node_id)
        self.db = load_database(dbc_path)
        self._nmt = self.db.get_message_by_name("NMT")
        self._by_name = {m.name: m for m in self.db.messages}
        offset = self.node_id - DBC_NODE_ID
        self.ids = {
            "EMCY": EMCY_BASE + self.node_id,
            "TPDO1": TPDO1_BASE + self.node_id,
            "TPDO2": TPDO2_BASE + self.node_id,
            "HEARTBEAT": HEARTBEAT_BASE + self.node_id,
        }
        self._name_by_id = {can_id: name for name, can_id in self.ids.items()}
        self._offset = offset

    def encode_nmt(self, command: str | int, node: int | None = None) -> tuple[int, bytes]:
        """NMT frame `(0x000, [cmd, node])`; `node=0` addresses all nodes, None this node."""
        cmd = NMT_COMMANDS[command] if isinstance(command, str) else int(command)
        target = self.node_id if node is None else int(node)
        data = self._nmt.encode({"command": cmd, "node_id": target}, scaling=False)
        return NMT_ID, bytes(data)

    def encode(self, name: str, values: dict) -> tuple[int, bytes]:
        """Any of the node's frames from raw signal values (tests, tools)."""
        return self.ids[name], bytes(self._by_name[name].encode(values, scaling=False))

    def frame_name(self, can_id: int) -> str | None:
        """'TPDO1', 'TPDO2', 'HEARTBEAT', 'EMCY', 'NMT' or None for another node's frame."""
        if can_id == NMT_ID:
            return "NMT"
        return self._name_by_id.get(can_id)

    def decode(self, can_id: int, data: bytes) -> tuple[str, dict] | None:
        """Raw (unscaled, integer) signal values of one of this node's frames, else None.

        ValueError if the frame is one of this node's but shorter than its DBC message.
        """
        name = self.frame_name(can_id)
        if name is None:
            return None
        message = self._by_name[name]
        if len(data) < message.length:
            raise ValueError(f"{name} frame 0x{can_id:03X} needs {message.length} bytes, got {len(data)}")
        return name, message.decode(bytes(data), decode_choices=False, scaling=False)

    def scale(self, message: str, signal: str) -> float:
        """The DBC factor of a signal (1e-6 g per µg count, 0.01 °C per count)."""
        return float(self._by_name[message].get_signal_by_name(signal).scale)


@dataclass
class AccelStats:
    """Counters of the node's traffic: pairs, unpaired frames, counter gaps, lost samples, EMCY."""

    pairs: int = 0
    unpaired: int = 0
    counter_gaps: int = 0
    lost_samples: int = 0
    emcy: int = 0
    heartbeats: int = 0
    frames: int = 0
    malformed: int = 0  # this node's IDs with too few data bytes: dropped (their sample is lost)

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass
class RawAccelSamples:
    """Paired samples as raw integers (µg, 0.01 °C) plus the unwrapped counter."""

    counter: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    accel_ug: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int64))
    temperature_centi_c: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    status: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))
    timestamp_s: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float64))

    def __len__(self) -> int:
        return len(self.counter)


class AccelFrameDecoder:
    """Pairs TPDO1/TPDO2 into samples; tracks heartbeat state and emergencies.

    Lost samples = counter gaps (missing counter values) + TPDO2 frames without their TPDO1
    (the sample's counter is known but its x, y are not). A TPDO1 followed by another TPDO1
    is counted as unpaired; its sample shows up as a counter gap at the next TPDO2.
    """

    def __init__(self, codec: CanCodec) -> None:
        self.codec = codec
        self.stats = AccelStats()
        self.heartbeat_state: int | None = None
        self.emergencies: list[Emcy] = []
        self._pending_xy: tuple[int, int] | None = None
        self._last_counter: int | None = None
        self._counter_index = 0
        self._rows: list[tuple[int, int, int, int, int, int, float]] = []

    def feed(self, can_id: int, data: bytes, timestamp: float | None = None,
             is_extended: bool = False, is_remote: bool = False) -> str | None:
        """Take one frame; returns the frame's name if it was one of this node's, else None.

        Never raises on bus input: a frame of this node shorter than its DBC message (a wrong
        DLC) is counted in ``stats.malformed`` and dropped like a lost frame (None is returned),
        so one bad frame cannot stop the driver's notifier thread.
        """
        if is_extended or is_remote:
            return None
        if self.codec.frame_name(can_id) == "NMT":  # commands from a host: nothing to decode
            return "NMT"
        try:
            decoded = self.codec.decode(can_id, data)
        except ValueError:
            self.stats.malformed += 1
            return None
        if decoded is None:
            return None
        name, sig = decoded
        self.stats.frames += 1
        if name == "TPDO1":
            if self._pending_xy is not None:
                self.stats.unpaired += 1
            self._pending_xy = (sig["accel_x"], sig["accel_y"])
        elif name == "TPDO2":
            counter = sig["counter"]
            if self._last_counter is None:
                self._counter_index = counter
            else:
                step = (counter - self._last_counter) % COUNTER_MODULO or COUNTER_MODULO
                if step > 1:
                    self.stats.counter_gaps += 1
                    self.stats.lost_samples += step - 1
                self._counter_index += step
            self._last_counter = counter
            if self._pending_xy is None:
                self.stats.unpaired += 1
                self.stats.lost_samples += 1
            else:
                x, y = self._pending_xy
                self._pending_xy = None
                self.stats.pairs += 1
                ts = float("nan") if timestamp is None else float(timestamp)
                self._rows.append((self._counter_index, x, y, sig["accel_z"], sig["temperature"],
                                   sig["status"], ts))
        elif name == "HEARTBEAT":
            self.stats.heartbeats += 1
            self.heartbeat_state = sig["state"]
        elif name == "EMCY":
            self.stats.emcy += 1
            code = sig["error_code"]
            meaning = EMCY_MEANINGS.get(code, f"error code 0x{code:04X}")
            self.emergencies.append(Emcy(code, sig["error_register"], meaning, bytes(data[3:8]), timestamp))
        return name

    def pending(self) -> int:
        """Samples paired and not yet drained."""
        return len(self._rows)

    def drain(self, max_samples: int | None = None) -> RawAccelSamples:
        """Hand over (and forget) the oldest paired samples."""
        k = len(self._rows) if max_samples is None else min(max_samples, len(self._rows))
        rows, self._rows = self._rows[:k], self._rows[k:]
        if not rows:
            return RawAccelSamples()
        ints = np.array([r[:6] for r in rows], dtype=np.int64)
        return RawAccelSamples(
            counter=ints[:, 0].copy(),
            accel_ug=ints[:, 1:4].copy(),
            temperature_centi_c=ints[:, 4].copy(),
            status=ints[:, 5].astype(np.uint8),
            timestamp_s=np.array([r[6] for r in rows], dtype=np.float64),
        )
