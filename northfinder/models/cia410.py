"""A CiA 410 inclinometer on CANopen (docs/PROTOCOLS.md §8, CiA DS 410 v1.2) as a :class:`TiltSensor`:
python-canopen with the unit's EDS (`northfinder/data/cia410.eds` for firmware_sim's node), the bytes
`northfinder.codecs.cia410`, the start-up and role mapping docs/second-models.md "CiA 410".

It stands on the accelerometer driver (`northfinder.drivers.accelerometer.Accelerometer`: bus,
python-canopen network and RemoteNode, NMT, heartbeat, EMCY, SDO, the one CAN log) and replaces
what is our node's own: the samples are TPDO1 with the profile's default mapping (0x6010 slope
long16, 0x6020 slope lateral16) and the rate is the profile's way, TPDO1 event-driven (0x1800:02 =
0xFE) with its event timer 0x1800:05 in ms. Slopes → degrees by the resolution 0x6000 → the unit
specific-force vector in g by `specific_force_from_slopes` (exact, docs/estimators.md §13).

The node has no sample counter: the counter of a sample is the ordinal of its TPDO1 among the
frames received (live and in replay the same rule over the same logged frames), so a lost frame is
not seen (`lost_samples` stays 0; docs/second-models.md). A slope at ±32767/−32768 counts is
saturated: the sample's status says so (bit 0) and its axis is NaN.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from northfinder.codecs import cia410
from northfinder.codecs.canopen import HEARTBEAT_STATES
from northfinder.devices.registry import ModelSpec
from northfinder.devices.tilt import AccelBlock, TiltDecoder, TiltSensor
from northfinder.drivers.accelerometer import Accelerometer
from northfinder.errors import DeviceError
from northfinder.models._section import value

DEVICE = "accelerometer"
DEFAULT_EDS_PATH = Path(__file__).resolve().parent.parent / "data" / "cia410.eds"
RESOLUTION_MDEG = 1
"""0x6000 written at start: 0.001° per LSB, the finest the profile has (17.45 µg at level)."""
EVENT_DRIVEN = 0xFE
SATURATED = 0x01
SDO_TIMEOUT_S = 2.0
"""Host seconds the SDO client waits for each answer. CiA 301 fixes none; our node's protocol says
1 s (PROTOCOLS.md §3.1). The profile's start-up is a dozen exchanges; on the loaded shared host one
find's configuration once stopped after the identity step at 1 s (not seen again at 2 s)."""


@dataclass
class SlopeStats:
    frames: int = 0
    malformed: int = 0
    saturated: int = 0
    heartbeats: int = 0
    emcy: int = 0
    lost_samples: int = 0

    def as_dict(self) -> dict[str, int]:
        """The counters; `pairs` is the samples' name in the run's faults (the accelerometer node's)."""
        return {**self.__dict__, "pairs": self.frames}


class SlopeDecoder:
    """TPDO1 frames of one node → (ordinal counter, slope counts); the same live and in replay."""

    def __init__(self, node_id: int) -> None:
        self.cob_id = cia410.TPDO1_BASE + int(node_id)
        self.stats = SlopeStats()
        self._counter: list[int] = []
        self._counts: list[tuple[int, int]] = []

    def feed(self, can_id: int, data: bytes, is_extended: bool = False, is_remote: bool = False) -> bool:
        """One received frame; True when it was a sample."""
        if can_id != self.cob_id or is_extended or is_remote:
            return False
        if len(data) != 4:
            self.stats.malformed += 1
            return False
        self._counter.append(self.stats.frames)
        self._counts.append(cia410.decode_slopes(bytes(data)))
        self.stats.frames += 1
        return True

    def pending(self) -> int:
        return len(self._counter)

    def drain(self, n: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        n = len(self._counter) if n is None else int(n)
        counter = np.asarray(self._counter[:n], dtype=np.int64)
        counts = np.asarray(self._counts[:n], dtype=np.int64).reshape(-1, 2)
        del self._counter[:n], self._counts[:n]
        return counter, counts


def slopes_to_block(counter: np.ndarray, counts: np.ndarray, resolution_mdeg: int) -> AccelBlock:
    """Slope counts → AccelBlock: the specific-force direction in g (|f| = 1 g: a slope carries no
    magnitude), NaN on a saturated axis (status bit 0)."""
    deg = cia410.deg_from_counts(counts, resolution_mdeg)
    f = cia410.specific_force_from_slopes(deg[:, 0], deg[:, 1], 1.0).reshape(-1, 3)
    sat = (counts >= 32767) | (counts <= -32768)
    f[:, :2][sat] = np.nan
    f[sat.any(axis=1), 2] = np.nan
    status = np.where(sat.any(axis=1), SATURATED, 0).astype(np.uint8)
    return AccelBlock(counter=np.asarray(counter, dtype=np.int64), accel_g=f,
                      temperature_c=np.full(len(counter), np.nan), status=status, lost_samples=0)


class Cia410Inclinometer(Accelerometer, TiltSensor):
    """A CiA 410 node in the tilt-sensor role: NMT start/stop, heartbeats as its status reports."""

    resolution_mdeg = RESOLUTION_MDEG

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._slopes = SlopeDecoder(int(kwargs.get("node_id", 0x10)))
        super().__init__(*args, **kwargs)

    # -- frames: TPDO1 are slopes, everything else as for the accelerometer node ----------
    def _on_frame(self, msg: Any) -> None:
        with self._lock:
            if not msg.is_error_frame and self._slopes.feed(msg.arbitration_id, bytes(msg.data),
                                                           msg.is_extended_id, msg.is_remote_frame):
                self._log(msg)
                if self._slopes.pending() >= self._want:  # the reader wakes once its count is there
                    self._lock.notify_all()
                return
        super()._on_frame(msg)

    # read (Accelerometer's) on the slopes
    _noun = "slopes"
    _silent_hint = "is the node operational and its TPDO1 event timer set?"

    def _queued(self) -> int:
        return self._slopes.pending()

    def _drain(self, k: int) -> Any:
        return self._slopes.drain(k)

    def _block(self, raw: Any) -> AccelBlock:
        block = slopes_to_block(*raw, self.resolution_mdeg)
        with self._lock:
            self._slopes.stats.saturated += int(np.count_nonzero(block.status))
        return block

    def discard_pending(self) -> int:
        with self._lock:
            return len(self._slopes.drain()[0])

    @property
    def stats(self) -> SlopeStats:
        with self._lock:
            base = self._decoder.stats
            return replace(self._slopes.stats, heartbeats=int(base.heartbeats), emcy=int(base.emcy))

    # -- the role ----------------------------------------------------------------------------
    def start_stream(self) -> None:
        self.start_node()

    def stop_stream(self) -> None:
        self.stop_node()

    def status_reports(self) -> int:
        return int(self._decoder.stats.heartbeats)

    def fault_reports(self) -> list[dict[str, Any]]:
        return [{"code": int(e.code), "register": int(e.register), "meaning": str(e.meaning)}
                for e in self.emergencies]

    def profile_identity(self) -> dict[str, Any]:
        """0x1000 (profile 410 in its low word), 0x1018, 0x1008; DeviceError for another profile."""
        device_type = int(self.sdo_read(0x1000, 0))
        if device_type & 0xFFFF != cia410.DEVICE_PROFILE:
            raise DeviceError(DEVICE, self.port, f"node 0x{self.node_id:02X} has device type "
                              f"0x{device_type:08X} (profile {device_type & 0xFFFF}), not a CiA 410 "
                              "inclinometer — check node_id and [accelerometer] model")
        return {**self.identity(), "device_type": device_type}

    def read_slope_mapping(self) -> str:
        """TPDO1's mapping read back (python-canopen); it must be 0x6010, 0x6020 (16 bits each)."""
        pdo = self.node.tpdo[1]
        try:
            pdo.read()
        except Exception as exc:  # noqa: BLE001 - SDO errors and EDS gaps alike: one line
            raise DeviceError(DEVICE, self.port, f"node 0x{self.node_id:02X}: cannot read the TPDO1 mapping "
                              f"({exc})") from None
        if pdo.cob_id:
            self.network.unsubscribe(pdo.cob_id, pdo.on_message)  # decoded here, not twice
        got = tuple((v.index, v.subindex, int(v.length)) for v in pdo.map)
        want = ((cia410.SLOPE_LONG16, 0, 16), (cia410.SLOPE_LATERAL16, 0, 16))
        text = ", ".join(f"{i:04X}:{s} ({n} bit)" for i, s, n in got) or "nothing"
        if got != want:
            raise DeviceError(DEVICE, self.port, f"node 0x{self.node_id:02X}: TPDO1 maps {text}; this driver "
                              "reads the profile's default 6010:0, 6020:0 (16 bit each)")
        return text

    def configure_for_run(self, section: Any, log_event: Callable[[dict[str, Any]], None]) -> dict[str, Any]:
        """Pre-operational; identity and profile; resolution 0.001°, no inversion or scaling; the rate
        by the TPDO1 event timer; the mapping read back; the heartbeat time. Each step an event."""
        self.wait_heartbeat()
        self.enter_pre_operational()
        log_event({"event": "accel_config", "step": "nmt", "state": "pre-operational"})
        ident = self.profile_identity()
        log_event({"event": "accel_config", "step": "identity", **ident})
        self.sdo_write(cia410.RESOLUTION, 0, self.resolution_mdeg)
        for obj in (cia410.SLOPE_LONG16_OPERATING, cia410.SLOPE_LATERAL16_OPERATING):
            self.sdo_write(obj, 0, 0)
        self.resolution_mdeg = int(self.sdo_read(cia410.RESOLUTION, 0))
        log_event({"event": "accel_config", "step": "resolution", "resolution_mdeg": self.resolution_mdeg,
                   "operating_parameters": 0})
        rate_hz = float(value(section, "rate_hz", 0.0) or 0.0)
        if int(self.sdo_read(0x1800, 2)) != EVENT_DRIVEN:
            self.sdo_write(0x1800, 2, EVENT_DRIVEN)
        if rate_hz > 0:
            self.sdo_write(0x1800, 5, int(round(1000.0 / rate_hz)))
        self.rate_hz = self.read_rate("1800:5")
        log_event({"event": "accel_config", "step": "rate", "object": "1800:5", "rate_hz": self.rate_hz,
                   "written": rate_hz > 0, "after_run": "left as configured (a reset node restores it)"})
        mapping = self.read_slope_mapping()
        log_event({"event": "accel_config", "step": "mapping", "mapping": mapping})
        hb_ms = value(section, "heartbeat_ms", 1000)
        if hb_ms is not None:
            self.sdo_write(0x1017, 0, int(hb_ms))
        hb = int(self.sdo_read(0x1017, 0))
        log_event({"event": "accel_config", "step": "heartbeat", "producer_ms": hb})
        return {"interface": self.interface, "channel": self.channel, "node_id": self.node_id,
                "rate_hz": self.rate_hz, "identity": ident, "resolution_mdeg": self.resolution_mdeg}

    def check_line(self) -> str:
        """Heartbeat state, profile and identity, resolution, rate and mapping — read only."""
        state = self.wait_heartbeat(timeout_s=3.0)
        if state == 0x04:
            self.enter_pre_operational()
        ident = self.profile_identity()
        rate_hz = self.read_rate("1800:5")
        res = int(self.sdo_read(cia410.RESOLUTION, 0))
        mapping = self.read_slope_mapping()
        name = HEARTBEAT_STATES.get(state, f"unknown 0x{state:02X}")
        return (f"accelerometer node 0x{self.node_id:02X} on {self.interface} {self.channel}: heartbeat "
                f"{name} (0x{state:02X}); CiA 410 inclinometer (device type 0x{ident['device_type']:08X}) "
                f"{ident['device_name']!r}, vendor ID 0x{ident['vendor_id']:08X}, product code "
                f"0x{ident['product_code']:08X}, revision 0x{ident['revision']:08X}, serial number "
                f"0x{ident['serial_number']:08X}; resolution {res * 1e-3:g}°; rate {rate_hz:g} Hz "
                f"(1800:5 event timer); TPDO1 {mapping}")


class Cia410LogDecoder(TiltDecoder):
    """can.asc of a run → slopes by the node id and resolution the run recorded (the live rule)."""

    def decode_log(self, path: Path, settings: dict[str, Any]) -> AccelBlock | None:
        import can

        if not Path(path).exists():
            return None
        dec = SlopeDecoder(int(settings["node_id"]))
        for m in can.LogReader(str(path)):
            if m.is_rx and not m.is_error_frame:
                dec.feed(m.arbitration_id, bytes(m.data), m.is_extended_id, m.is_remote_frame)
        counter, counts = dec.drain()
        return slopes_to_block(counter, counts, int(settings.get("resolution_mdeg", RESOLUTION_MDEG)))


def _open(section: Any, log_path: Any, options: dict[str, Any]) -> Cia410Inclinometer:
    bus_options = {**options.get("can_kwargs", {}), **value(section, "bus_options", {})}
    return Cia410Inclinometer(value(section, "interface", "slcan"), value(section, "channel", ""),
                              bitrate=value(section, "bitrate", 500_000),
                              node_id=value(section, "node_id", 0x10),
                              rate_hz=value(section, "rate_hz", 0.0) or 100.0,
                              eds_path=options.get("eds_path") or DEFAULT_EDS_PATH, log_path=log_path,
                              sdo_timeout_s=SDO_TIMEOUT_S,
                              bus_options=bus_options or None)


SPEC = ModelSpec("accelerometer", "cia410", _open, Cia410LogDecoder,
                 "CiA 410 inclinometer on CANopen (python-canopen, the unit's EDS)")
