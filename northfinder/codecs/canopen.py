"""CANopen accelerometer node (docs/PROTOCOLS.md §3, §3.1): frames ⇄ values, no I/O.

TPDOs are decoded by a :class:`PdoLayout` — the mapping the driver reads from the node over SDO
(objects, bit lengths, and their scale and unit from the EDS); :func:`default_layout` is the
reference node's (§3.1 defaults). NMT, heartbeat and EMCY frames (and the TPDOs of the default
mapping, for raw CAN logs in common tools) are described by ``northfinder/data/accelerometer.dbc``
(IDs for node 0x10; another node ID uses the same bases 0x080, 0x180, 0x280, 0x700 plus its ID).

:class:`AccelFrameDecoder` is the stateful part shared by the live driver and the replay path:
it assembles one frame of each TPDO into a sample (the last TPDO, which carries the counter,
closes it), unwraps the 8-bit counter, counts unpaired frames, counter gaps and lost samples,
and keeps heartbeats and emergencies.
"""

from __future__ import annotations

import functools
import struct
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import cantools
import numpy as np

from northfinder.devices.tilt import AccelBlock  # the role's data type, re-exported

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
    "MappedObject",
    "PdoLayout",
    "TpdoLayout",
    "default_layout",
    "load_database",
    "object_role",
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
    """Paired samples as raw integers of the mapped objects plus the unwrapped counter (for the
    reference mapping: µg and 0.01 °C)."""

    counter: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    accel_raw: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int64))
    temperature_raw: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    status: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))
    timestamp_s: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float64))

    @property
    def accel_ug(self) -> np.ndarray:
        """The raw axis values (µg with the reference mapping; see the layout's scale otherwise)."""
        return self.accel_raw

    def __len__(self) -> int:
        return len(self.counter)


# -- the TPDO mapping, read from the node (or the EDS defaults) -------------------------------
UNIT_SCALE = {"g": 1.0, "mg": 1e-3, "ug": 1e-6, "µg": 1e-6, "m/s2": 1 / 9.80665, "m/s^2": 1 / 9.80665,
              "degc": 1.0, "°c": 1.0, "c": 1.0, "": 1.0}
"""An EDS `Unit` → the edge unit (g for acceleration, °C for temperature) per unit."""
ROLES = ("x", "y", "z", "temperature", "counter", "status")
_INT = {(8, False): "B", (16, False): "H", (32, False): "I", (8, True): "b", (16, True): "h", (32, True): "i"}


def object_role(name: str) -> str | None:
    """What a mapped object is, from its EDS ParameterName: an axis, temperature, counter, status."""
    low = name.strip().lower()
    if "accel" in low and low[-1:] in ("x", "y", "z") and (len(low) < 2 or not low[-2].isalpha()):
        return low[-1]
    for role in ("temperature", "counter", "status"):
        if role in low:
            return role
    return None


@dataclass(frozen=True)
class MappedObject:
    """One entry of a TPDO mapping: the object, its bits, and what it means (from the EDS)."""

    index: int
    sub: int
    bits: int
    signed: bool
    name: str = ""
    role: str | None = None
    scale: float = 1.0  # raw × scale → g (axes) or °C (temperature)
    unit: str = ""

    @property
    def label(self) -> str:
        return f"{self.index:04X}:{self.sub} {self.name}".strip()


@dataclass(frozen=True)
class TpdoLayout:
    """One TPDO: its COB-ID and the objects mapped into it, in order."""

    number: int
    cob_id: int
    objects: tuple[MappedObject, ...]

    @property
    def length(self) -> int:
        return sum(o.bits for o in self.objects) // 8

    @property
    def fmt(self) -> str:
        return "<" + "".join(_INT[(o.bits, o.signed)] for o in self.objects)


@dataclass(frozen=True)
class PdoLayout:
    """The node's TPDOs in transmission order; the last one closes a sample and carries its counter."""

    tpdos: tuple[TpdoLayout, ...]

    def find(self, role: str) -> MappedObject | None:
        for t in self.tpdos:
            for o in t.objects:
                if o.role == role:
                    return o
        return None

    def problems(self) -> list[str]:
        """What keeps this mapping from giving samples (empty if it is usable)."""
        out = []
        for o in (o for t in self.tpdos for o in t.objects):
            if (o.bits, o.signed) not in _INT:
                out.append(f"object {o.label} is mapped with {o.bits} bits; only 8/16/32-bit integers decode")
        for role in ("x", "y", "z", "counter"):
            if self.find(role) is None:
                out.append(f"no mapped object is the {role if role == 'counter' else 'acceleration ' + role}"
                           " (an EDS ParameterName such as 'Acceleration x' / 'Sample counter')")
        if self.tpdos and not any(o.role == "counter" for o in self.tpdos[-1].objects):
            out.append(f"the sample counter must be in the last TPDO (COB-ID 0x{self.tpdos[-1].cob_id:03X})")
        return out

    def describe(self) -> str:
        """`TPDO1 0x190: 2000:1 Acceleration x (1 ug), …; TPDO2 …` for check and the events."""
        parts = []
        for t in self.tpdos:
            objs = ", ".join(f"{o.label}" + (f" ({o.scale / UNIT_SCALE.get(o.unit.lower(), 1.0):g} {o.unit})"
                                              if o.unit else "") for o in t.objects)
            parts.append(f"TPDO{t.number} 0x{t.cob_id:03X}: {objs}")
        return "; ".join(parts)

    def to_dict(self) -> dict:
        return {"tpdos": [{"number": t.number, "cob_id": t.cob_id,
                           "objects": [dict(o.__dict__) for o in t.objects]} for t in self.tpdos]}

    @classmethod
    def from_dict(cls, data: dict) -> PdoLayout:
        return cls(tuple(TpdoLayout(int(t["number"]), int(t["cob_id"]),
                                    tuple(MappedObject(**o) for o in t["objects"])) for t in data["tpdos"]))


def _ref(index: int, sub: int, bits: int, signed: bool, name: str, role: str, scale: float,
         unit: str) -> MappedObject:
    return MappedObject(index, sub, bits, signed, name, role, scale, unit)


def default_layout(node_id: int = DBC_NODE_ID) -> PdoLayout:
    """The reference node's mapping (PROTOCOLS.md §3.1 defaults, = the DBC's TPDO1/TPDO2)."""
    return PdoLayout((
        TpdoLayout(1, TPDO1_BASE + node_id, (
            _ref(0x2000, 1, 32, True, "Acceleration x", "x", 1e-6, "ug"),
            _ref(0x2000, 2, 32, True, "Acceleration y", "y", 1e-6, "ug"))),
        TpdoLayout(2, TPDO2_BASE + node_id, (
            _ref(0x2000, 3, 32, True, "Acceleration z", "z", 1e-6, "ug"),
            _ref(0x2001, 0, 16, True, "Temperature", "temperature", 0.01, "degC"),
            _ref(0x2002, 0, 8, False, "Sample counter", "counter", 1.0, ""),
            _ref(0x2003, 0, 8, False, "Status", "status", 1.0, ""))),
    ))


class AccelFrameDecoder:
    """Assembles samples from the node's TPDOs by a mapping (:class:`PdoLayout`); tracks heartbeat
    state and emergencies.

    A sample is one frame of each TPDO in order; the last TPDO (which carries the counter)
    completes it. Lost samples = counter gaps (missing counter values) + closing frames whose
    earlier TPDOs did not arrive. An earlier TPDO seen twice before its closing frame counts as
    unpaired; its sample shows up as a counter gap.
    """

    def __init__(self, codec: CanCodec, layout: PdoLayout | None = None) -> None:
        self.codec = codec
        self.stats = AccelStats()
        self.heartbeat_state: int | None = None
        self.emergencies: list[Emcy] = []
        self._last_counter: int | None = None
        self._counter_index = 0
        self._rows: list[tuple] = []
        self.set_layout(layout or default_layout(codec.node_id))

    def set_layout(self, layout: PdoLayout) -> None:
        """Decode by `layout` from now on (the mapping read from the node)."""
        problems = layout.problems()
        if problems:
            raise ValueError(problems[0])
        self.layout = layout
        self._tpdo = {t.cob_id: (k, t, struct.Struct(t.fmt)) for k, t in enumerate(layout.tpdos)}
        self._last = len(layout.tpdos) - 1
        self._pending: dict[int, tuple] = {}
        roles = [(o.role, k, j) for k, t in enumerate(layout.tpdos) for j, o in enumerate(t.objects)]
        self._where = {role: (k, j) for role, k, j in roles if role is not None}

    def names(self) -> dict[int, str]:
        """COB-ID → 'TPDO<n>' for this layout."""
        return {t.cob_id: f"TPDO{t.number}" for t in self.layout.tpdos}

    def feed(self, can_id: int, data: bytes, timestamp: float | None = None,
             is_extended: bool = False, is_remote: bool = False, node_frames: bool = True) -> str | None:
        """Take one frame; returns the frame's name if it was one of this node's, else None.

        `node_frames=False`: only TPDOs are decoded here (the live driver gets heartbeats and
        EMCY through python-canopen). Never raises on bus input: a frame of this node shorter
        than its mapping or message (a wrong DLC) is counted in ``stats.malformed`` and dropped.
        """
        if is_extended or is_remote:
            return None
        hit = self._tpdo.get(can_id)
        if hit is not None:
            k, tpdo, st = hit
            if len(data) < st.size:
                self.stats.malformed += 1
                return None
            self.stats.frames += 1
            self._on_tpdo(k, st.unpack_from(bytes(data)), timestamp)
            return f"TPDO{tpdo.number}"
        if not node_frames:
            return None
        if can_id == NMT_ID:  # commands from a host: nothing to decode
            return "NMT"
        name = self.codec.frame_name(can_id)
        if name not in ("HEARTBEAT", "EMCY"):
            return None
        try:
            _, sig = self.codec.decode(can_id, data)
        except ValueError:
            self.stats.malformed += 1
            return None
        self.stats.frames += 1
        if name == "HEARTBEAT":
            self.on_heartbeat(sig["state"])
        else:
            self.on_emcy(sig["error_code"], sig["error_register"], bytes(data[3:8]), timestamp)
        return name

    def on_heartbeat(self, state: int) -> None:
        self.stats.heartbeats += 1
        self.heartbeat_state = int(state)

    def on_emcy(self, code: int, register: int, vendor: bytes, timestamp: float | None) -> None:
        self.stats.emcy += 1
        meaning = EMCY_MEANINGS.get(code, f"error code 0x{code:04X}")
        self.emergencies.append(Emcy(int(code), int(register), meaning, bytes(vendor), timestamp))

    def _on_tpdo(self, k: int, values: tuple, timestamp: float | None) -> None:
        if k < self._last:
            if k in self._pending:
                self.stats.unpaired += 1
            self._pending[k] = values
            return
        pending, self._pending = self._pending, {}
        ck, cj = self._where["counter"]
        counter = values[cj]
        if self._last_counter is None:
            self._counter_index = counter
        else:
            step = (counter - self._last_counter) % COUNTER_MODULO or COUNTER_MODULO
            if step > 1:
                self.stats.counter_gaps += 1
                self.stats.lost_samples += step - 1
            self._counter_index += step
        self._last_counter = counter
        if len(pending) < self._last:
            self.stats.unpaired += 1
            self.stats.lost_samples += 1
            return
        pending[k] = values
        self.stats.pairs += 1

        def get(role: str, default: int) -> int:
            where = self._where.get(role)
            return default if where is None else pending[where[0]][where[1]]

        ts = float("nan") if timestamp is None else float(timestamp)
        self._rows.append((self._counter_index, get("x", 0), get("y", 0), get("z", 0),
                           get("temperature", 0), get("status", 0x07), ts))

    def pending(self) -> int:
        """Samples complete and not yet drained."""
        return len(self._rows)

    def drain(self, max_samples: int | None = None) -> RawAccelSamples:
        """Hand over (and forget) the oldest complete samples."""
        k = len(self._rows) if max_samples is None else min(max_samples, len(self._rows))
        rows, self._rows = self._rows[:k], self._rows[k:]
        if not rows:
            return RawAccelSamples()
        ints = np.array([r[:6] for r in rows], dtype=np.int64)
        return RawAccelSamples(
            counter=ints[:, 0].copy(),
            accel_raw=ints[:, 1:4].copy(),
            temperature_raw=ints[:, 4].copy(),
            status=ints[:, 5].astype(np.uint8),
            timestamp_s=np.array([r[6] for r in rows], dtype=np.float64),
        )


# -- decoded samples in edge units (the live driver and replay share these) --------------------
def _divisor(scale: float) -> float:
    """1e-6 → 1e6: dividing by the exact integer rounds µg → g correctly."""
    inv = 1.0 / scale
    return float(round(inv)) if abs(inv - round(inv)) < 1e-9 * inv else inv


def samples_to_block(raw: RawAccelSamples, layout: PdoLayout) -> AccelBlock:
    """Raw samples → an AccelBlock in g and °C, each axis scaled by its mapped object's EDS unit."""
    counter = np.asarray(raw.counter, dtype=np.int64)
    lost = int(counter[-1] - counter[0] + 1 - len(counter)) if len(counter) else 0
    accel = np.empty(raw.accel_raw.shape, dtype=np.float64)
    for j, role in enumerate("xyz"):
        accel[:, j] = raw.accel_raw[:, j].astype(np.float64) / _divisor(layout.find(role).scale)
    temp_obj = layout.find("temperature")
    temperature = (raw.temperature_raw.astype(np.float64) / _divisor(temp_obj.scale) if temp_obj is not None
                   else np.full(len(counter), np.nan))
    return AccelBlock(counter=counter, accel_g=accel, temperature_c=temperature,
                      status=raw.status.astype(np.uint8), lost_samples=lost)


def decode_accel_frames(frames: Iterable[tuple[int, bytes, float, bool, bool]], node_id: int = 0x10,
                        dbc_path: str | Path | None = None,
                        layout: PdoLayout | dict | None = None) -> tuple[AccelBlock, AccelStats]:
    """Decode received frames `(can_id, data, timestamp, is_extended, is_remote)` of the node's
    traffic (replay of a CAN log) by `layout` (the mapping the run read; default the reference)."""
    codec = CanCodec(node_id, dbc_path)
    if isinstance(layout, dict):
        layout = PdoLayout.from_dict(layout)
    decoder = AccelFrameDecoder(codec, layout)
    for can_id, data, timestamp, is_extended, is_remote in frames:
        decoder.feed(can_id, data, timestamp, is_extended, is_remote)
    return samples_to_block(decoder.drain(), decoder.layout), decoder.stats
