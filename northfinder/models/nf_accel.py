"""northfinder's CANopen accelerometer node (docs/PROTOCOLS.md §3, §3.1) as a :class:`TiltSensor`: the
driver `northfinder.drivers.accelerometer.Accelerometer` (python-canopen), the bytes
`northfinder.codecs.canopen`."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from northfinder.codecs.canopen import HEARTBEAT_STATES, decode_accel_frames
from northfinder.devices.registry import ModelSpec
from northfinder.devices.tilt import AccelBlock, TiltDecoder, TiltSensor
from northfinder.drivers.accelerometer import Accelerometer
from northfinder.models._section import value


class NfAccel(Accelerometer, TiltSensor):
    """Our node in the tilt-sensor role: NMT start/stop, heartbeats as its status reports."""

    def start_stream(self) -> None:
        self.start_node()

    def stop_stream(self) -> None:
        self.stop_node()

    def status_reports(self) -> int:
        return int(self.stats.heartbeats)

    def fault_reports(self) -> list[dict[str, Any]]:
        return [{"code": int(e.code), "register": int(e.register), "meaning": str(e.meaning)}
                for e in self.emergencies]

    rate_object = "2100:0"

    def check_line(self) -> str:
        return _check_line(self, self.rate_object)

    def configure_for_run(self, section: Any, log_event: Callable[[dict[str, Any]], None]) -> dict[str, Any]:
        """Wait for the node, configure it over SDO (identity, mapping, rate, heartbeat time: each
        step an event); what the start event records."""
        self.wait_heartbeat()
        info = self.configure(rate_hz=value(section, "rate_hz", 0.0) or None,
                              heartbeat_ms=value(section, "heartbeat_ms", 1000),
                              rate_object=value(section, "rate_object", "2100:0"), log=log_event)
        return {"interface": self.interface, "channel": self.channel, "node_id": self.node_id,
                "rate_hz": self.rate_hz, "identity": info["identity"], "layout": self.layout.to_dict()}


def _check_line(acc: NfAccel, rate_object: str) -> str:
    """Heartbeat state, identity (0x1018, 0x1008), rate and mapping — read only, nothing written."""
    state = acc.wait_heartbeat(timeout_s=3.0)
    if state == 0x04:  # stopped: CiA 301 has no SDO there; pre-operational changes nothing else
        acc.enter_pre_operational()
    ident = acc.identity()
    layout = acc.read_mapping()
    rate_hz = acc.read_rate(rate_object)
    name = HEARTBEAT_STATES.get(state, f"unknown 0x{state:02X}")
    return (
        f"accelerometer node 0x{acc.node_id:02X} on {acc.interface} {acc.channel}: heartbeat {name} "
        f"(0x{state:02X}); "
        f"{ident['device_name']!r}, vendor ID 0x{ident['vendor_id']:08X}, product code "
        f"0x{ident['product_code']:08X}, revision 0x{ident['revision']:08X}, serial number "
        f"0x{ident['serial_number']:08X}; rate {rate_hz:g} Hz ({rate_object}); mapping {layout.describe()}"
    )


class CanLogDecoder(TiltDecoder):
    """can.asc of a run → samples, by the node id and mapping the run recorded."""

    def decode_log(self, path: Path, settings: dict[str, Any]) -> AccelBlock | None:
        import can

        if not Path(path).exists():
            return None
        frames = ((m.arbitration_id, bytes(m.data), m.timestamp, m.is_extended_id, m.is_remote_frame)
                  for m in can.LogReader(str(path)) if m.is_rx and not m.is_error_frame)
        block, _ = decode_accel_frames(frames, node_id=settings["node_id"], layout=settings.get("layout"))
        return block


def _open(section: Any, log_path: Any, options: dict[str, Any]) -> NfAccel:
    bus_options = {**options.get("can_kwargs", {}), **value(section, "bus_options", {})}
    acc = NfAccel(value(section, "interface", "slcan"), value(section, "channel", ""),
                   bitrate=value(section, "bitrate", 500_000), node_id=value(section, "node_id", 0x10),
                   rate_hz=value(section, "rate_hz", 0.0) or 100.0, eds_path=options.get("eds_path"),
                   log_path=log_path, bus_options=bus_options or None)
    acc.rate_object = value(section, "rate_object", "2100:0")
    return acc


SPEC = ModelSpec("accelerometer", "nf-accel", _open, CanLogDecoder,
                 "northfinder's CANopen accelerometer node (python-canopen, EDS)")
