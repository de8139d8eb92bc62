"""The CANopen conformance table: every object of firmware-sim's node and every CiA 301 rule for
the PDO communication/mapping parameters and SYNC, sent to the node over SDO and the bus → what
it answers (value, SDO abort code, frames on the bus) → what CiA 301 says.

The expectations are written here from CiA 301 v4.2 (§7.2.2 PDO, §7.2.5 SYNC, §7.5.2.5 1005h,
§7.5.2.37 1800h, §7.5.2.38 1A00h, §7.2.4.3.17 abort codes), independently of the node's own
checks. Writes docs/conformance/canopen.md, prints the row count and every row that differs;
exit status 1 when any does.

    python tools/conformance_canopen.py [--out docs/conformance/canopen.md]
"""

from __future__ import annotations

import argparse
import itertools
import struct
import sys
from collections.abc import Callable
from pathlib import Path

import can
import numpy as np

from firmware_sim.devices import canopen_accel as ca
from firmware_sim.devices.canopen_accel import CanAccelNode

OUT = Path(__file__).resolve().parents[1] / "docs" / "conformance" / "canopen.md"
NODE = 0x10
PRE, OP = ca.STATE_PRE_OPERATIONAL, ca.STATE_OPERATIONAL
_channels = itertools.count()

ABORT_TEXT = {
    0x06010000: "unsupported access to an object", 0x06010002: "attempt to write a read only object",
    0x06020000: "object does not exist", 0x06040041: "object cannot be mapped to the PDO",
    0x06040042: "number and length of mapped objects exceed PDO length",
    0x06070010: "data type does not match, length of service parameter does not match",
    0x06090011: "sub-index does not exist", 0x06090030: "invalid value for parameter (download only)",
    0x08000022: "data cannot be transferred because of the present device state",
}


class _World:
    """1 g on z, nothing else (the conformance rows test bytes and timing, not physics)."""

    def increments(self, t0_s, n, dt_s, lever_arm_b_m):
        return np.zeros((n, 3)), np.tile(np.array([0.0, 0.0, 9.80665 * dt_s]), (n, 1))


class _Perfect:
    def apply(self, dv):
        return np.asarray(dv, dtype=float)


class Bench:
    """The node on one end of a virtual bus, a bare master on the other; device time by hand."""

    def __init__(self) -> None:
        channel = f"conformance-{next(_channels)}"
        self.node_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.master = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.node = CanAccelNode(self.node_bus, _World(), _Perfect(), node_id=NODE, rate_hz=100.0)
        self.t = 0.0
        self.node.advance(0.0)
        self.drain()

    def close(self) -> None:
        self.node_bus.shutdown()
        self.master.shutdown()

    def drain(self) -> list[can.Message]:
        return list(iter(lambda: self.master.recv(timeout=0), None))

    def step(self, dt: float) -> list[can.Message]:
        self.t += dt
        self.node.advance(self.t)
        return self.drain()

    def sdo(self, request: bytes) -> bytes | None:
        self.master.send(can.Message(arbitration_id=0x600 + NODE, data=request, is_extended_id=False))
        replies = [m for m in self.step(0.0) if m.arbitration_id == 0x580 + NODE]
        return bytes(replies[-1].data) if replies else None

    def write(self, index: int, sub: int, kind: str, value: int) -> str:
        data = struct.pack("<" + {"u8": "B", "u16": "H", "u32": "I"}[kind], value)
        return _answer(self.sdo(ca.sdo_download_request(index, sub, data)))

    def read(self, index: int, sub: int) -> str:
        return _answer(self.sdo(ca.sdo_upload_request(index, sub)))

    def nmt(self, command: int) -> None:
        self.master.send(can.Message(arbitration_id=0, data=[command, NODE], is_extended_id=False))
        self.step(0.0)


def _answer(reply: bytes | None) -> str:
    if reply is None:
        return "no reply"
    if reply[0] == 0x80:
        return f"abort 0x{struct.unpack_from('<I', reply, 4)[0]:08X}"
    if reply[0] == 0x60:
        return "ok"
    if reply[0] == 0x41:
        return f"segmented, {struct.unpack_from('<I', reply, 4)[0]} bytes"
    n = 4 - ((reply[0] >> 2) & 3)
    return f"0x{int.from_bytes(reply[4:4 + n], 'little'):0{2 * n}X}"


def _abort(code: int) -> str:
    return f"abort 0x{code:08X} ({ABORT_TEXT[code]})"


def _invalidate(b: Bench, pdo: int = 0) -> None:
    b.write(0x1800 + pdo, 1, "u32", ca.PDO_NOT_VALID | (0x180 + 0x100 * pdo + NODE))


Row = tuple[str, str, str, str, bool]  # object/rule, action, node answers, CiA 301 says, agrees


def object_rows() -> list[Row]:
    """Read every object; write a read-only one (abort 0x06010002) or write back a rw one."""
    out: list[Row] = []
    b = Bench()
    for (index, sub), entry in sorted(b.node.od.items()):
        got = b.read(index, sub)
        want = "segmented" if entry.kind == "vs" and len(entry.encode()) > 4 else "expedited value"
        ok = got.startswith("segmented") if want == "segmented" else got.startswith("0x")
        out.append((f"{index:04X}:{sub}", "read", got, want, ok))
        if entry.access == "ro":
            kind = entry.kind if entry.kind in ("u8", "u16", "u32") else "u32"
            got = b.write(index, sub, kind, 0)
            out.append((f"{index:04X}:{sub}", "write", got, _abort(0x06010002), got == "abort 0x06010002"))
    out.append(("1800:4", "read", b.read(0x1800, 4), "reserved: " + _abort(0x06090011),
                b.read(0x1800, 4) == "abort 0x06090011"))
    got = b.read(0x2200, 0)
    out.append(("2200:0", "read", got, _abort(0x06020000), got == "abort 0x06020000"))
    b.nmt(ca.NMT_STOP)
    got = b.read(0x1000, 0)
    out.append(("1000:0 in STOPPED", "read", got, "no reply (no SDO in stopped, §7.3.2.2.2)",
                got == "no reply"))
    b.close()
    return out


def _rule(what: str, action: str, setup: Callable[[Bench], None], do: Callable[[Bench], str],
          want: str, expect: str) -> Row:
    b = Bench()
    setup(b)
    got = do(b)
    b.close()
    return what, action, got, want, got == expect


def _frames(b: Bench, cob_id: int, frames: list[can.Message]) -> list[can.Message]:
    return [m for m in frames if m.arbitration_id == cob_id]


def rule_rows() -> list[Row]:
    """The access rules of 1005h, 1800h, 1A00h and the mapping procedure's abort codes."""
    none = lambda b: None  # noqa: E731
    inv = _invalidate
    empty = lambda b: (inv(b), b.write(0x1A00, 0, "u8", 0))  # noqa: E731 - procedure steps 1 and 2
    cob1 = 0x180 + NODE
    rows = [
        _rule("1800:1 COB-ID", "set bit 31 (invalidate)", none,
              lambda b: b.write(0x1800, 1, "u32", ca.PDO_NOT_VALID | cob1), "ok", "ok"),
        _rule("1800:1 COB-ID", "other CAN-ID while valid", none,
              lambda b: b.write(0x1800, 1, "u32", cob1 + 1), _abort(0x06090030), "abort 0x06090030"),
        _rule("1800:1 COB-ID", "other CAN-ID while not valid", inv,
              lambda b: b.write(0x1800, 1, "u32", ca.PDO_NOT_VALID | 0x1A0), "ok", "ok"),
        _rule("1800:1 COB-ID", "bit 29 (29-bit ID) on an 11-bit node", inv,
              lambda b: b.write(0x1800, 1, "u32", ca.PDO_NOT_VALID | 1 << 29 | cob1),
              _abort(0x06090030), "abort 0x06090030"),
        _rule("1800:1 COB-ID", "clear bit 31 (validate)", inv,
              lambda b: b.write(0x1800, 1, "u32", cob1), "ok", "ok"),
    ]
    for ttype in (0, 1, 240, 252, 253, 254, 255):
        rows.append(_rule("1800:2 transmission type", f"write {ttype}", none,
                          lambda b, v=ttype: b.write(0x1800, 2, "u8", v), "ok", "ok"))
    for ttype in (241, 251):
        rows.append(_rule("1800:2 transmission type", f"write {ttype} (reserved)", none,
                          lambda b, v=ttype: b.write(0x1800, 2, "u8", v),
                          _abort(0x06090030), "abort 0x06090030"))
    rows += [
        _rule("1800:3 inhibit time", "write while valid", none,
              lambda b: b.write(0x1800, 3, "u16", 10), _abort(0x06090030), "abort 0x06090030"),
        _rule("1800:3 inhibit time", "write while not valid", inv,
              lambda b: b.write(0x1800, 3, "u16", 10), "ok", "ok"),
        _rule("1800:5 event timer", "write while valid", none,
              lambda b: b.write(0x1800, 5, "u16", 50), "ok", "ok"),
        _rule("1800:6 SYNC start value", "write while valid", none,
              lambda b: b.write(0x1800, 6, "u8", 3), _abort(0x06090030), "abort 0x06090030"),
        _rule("1800:6 SYNC start value", "write while not valid", inv,
              lambda b: b.write(0x1800, 6, "u8", 3), "ok", "ok"),
        _rule("1A00:0 mapping count", "write while the PDO is valid", none,
              lambda b: b.write(0x1A00, 0, "u8", 0), _abort(0x06010000), "abort 0x06010000"),
        _rule("1A00:1 mapping entry", "write while the count is not 0", inv,
              lambda b: b.write(0x1A00, 1, "u32", 0x20000320), _abort(0x06010000), "abort 0x06010000"),
        _rule("1A00:0 mapping count", "procedure step 2: count 0", inv,
              lambda b: b.write(0x1A00, 0, "u8", 0), "ok", "ok"),
        _rule("1A00:1 mapping entry", "procedure step 3: an entry", empty,
              lambda b: b.write(0x1A00, 1, "u32", 0x20000320), "ok", "ok"),
        _rule("1A00:1 mapping entry", "an object that does not exist", empty,
              lambda b: b.write(0x1A00, 1, "u32", 0x22000020), _abort(0x06020000), "abort 0x06020000"),
        _rule("1A00:1 mapping entry", "an object not mappable (1017h)", empty,
              lambda b: b.write(0x1A00, 1, "u32", 0x10170010), _abort(0x06040041), "abort 0x06040041"),
        _rule("1A00:1 mapping entry", "a wrong length (8-bit object as 32)",
              empty,
              lambda b: b.write(0x1A00, 1, "u32", 0x20020020), _abort(0x06040041), "abort 0x06040041"),
        _rule("1A00:0 mapping count", "procedure step 4: 96 bits",
              lambda b: (inv(b), b.write(0x1A00, 0, "u8", 0), b.write(0x1A00, 3, "u32", 0x20000320)),
              lambda b: b.write(0x1A00, 0, "u8", 3), _abort(0x06040042), "abort 0x06040042"),
        _rule("1A00:0 mapping count", "procedure step 4: 40 bits",
              lambda b: (inv(b), b.write(0x1A00, 0, "u8", 0), b.write(0x1A00, 2, "u32", 0x20020008)),
              lambda b: b.write(0x1A00, 0, "u8", 2), "ok", "ok"),
        _rule("1005:0 COB-ID SYNC", "write 0x81", none,
              lambda b: b.write(0x1005, 0, "u32", 0x81), "ok", "ok"),
        _rule("1005:0 COB-ID SYNC", "bit 30 (produce SYNC) on a consumer", none,
              lambda b: b.write(0x1005, 0, "u32", 0x40000080), _abort(0x06090030), "abort 0x06090030"),
    ]
    return rows


def _run_op(setup: Callable[[Bench], None], drive: Callable[[Bench], list[can.Message]]) -> list[can.Message]:
    b = Bench()
    setup(b)
    b.nmt(ca.NMT_START)
    frames = drive(b)
    b.close()
    return frames


def _sync_then(n_sync: int, step_s: float = 0.01,
               first_s: float = 0.005) -> Callable[[Bench], list[can.Message]]:
    def drive(b: Bench) -> list[can.Message]:
        frames = b.step(first_s)
        for _ in range(n_sync):
            frames += b.step(step_s)
            b.master.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
            frames += b.step(0.0)
        return frames
    return drive


def _ttype(value: int, **extra: int) -> Callable[[Bench], None]:
    def setup(b: Bench) -> None:
        _invalidate(b)
        for sub, v in extra.items():
            b.write(0x1800, int(sub[1:]), "u16" if sub in ("s3", "s5") else "u8", v)
        b.write(0x1800, 2, "u8", value)
        b.write(0x1800, 1, "u32", 0x180 + NODE)
    return setup


def behaviour_rows() -> list[Row]:
    """What goes onto the bus for each transmission type (CiA 301 §7.2.2.2)."""
    cob1 = 0x180 + NODE
    rows: list[Row] = []

    def count(frames: list[can.Message]) -> int:
        return sum(m.arbitration_id == cob1 for m in frames)

    got = count(_run_op(lambda b: None, lambda b: b.step(1.0)))
    rows.append(("TPDO1 type 254, timer 0", "1 s at 100 Hz", f"{got} TPDO1",
                 "one per sample (the event): 100", got == 100))
    got = count(_run_op(_ttype(254, s5=50), lambda b: b.step(1.0)))
    rows.append(("TPDO1 type 254, event timer 50 ms", "1 s", f"{got} TPDO1", "one per 50 ms: 20", got == 20))
    got = count(_run_op(_ttype(254, s3=250), lambda b: b.step(1.0)))
    rows.append(("TPDO1 type 254, inhibit 25 ms", "1 s at 100 Hz", f"{got} TPDO1",
                 "no two within 25 ms: 40", got == 40))
    got = count(_run_op(_ttype(1), lambda b: b.step(1.0)))
    rows.append(("TPDO1 type 1", "1 s, no SYNC", f"{got} TPDO1", "nothing without SYNC: 0", got == 0))
    got = count(_run_op(_ttype(1), _sync_then(6)))
    rows.append(("TPDO1 type 1", "6 SYNC", f"{got} TPDO1", "one per SYNC: 6", got == 6))
    got = count(_run_op(_ttype(3), _sync_then(9)))
    rows.append(("TPDO1 type 3", "9 SYNC", f"{got} TPDO1", "every 3rd SYNC: 3", got == 3))
    got = count(_run_op(_ttype(0), _sync_then(4, step_s=0.0, first_s=0.015)))
    rows.append(("TPDO1 type 0 (acyclic synchronous)", "4 SYNC, one new sample before the first",
                 f"{got} TPDO1", "on the SYNC after an event only: 1", got == 1))

    def rtr(b: Bench) -> list[can.Message]:
        frames = b.step(0.05)
        b.master.send(can.Message(arbitration_id=cob1, is_remote_frame=True, dlc=8, is_extended_id=False))
        return frames + b.step(0.0)
    got = count(_run_op(_ttype(253), rtr))
    rows.append(("TPDO1 type 253 (RTR only)", "0.05 s, then one RTR", f"{got} TPDO1", "on RTR only: 1",
                 got == 1))

    def start_value(b: Bench) -> list[can.Message]:
        frames = b.step(0.005)
        for counter in range(1, 7):
            frames += b.step(0.01)
            b.master.send(can.Message(arbitration_id=0x080, data=bytes((counter,)), is_extended_id=False))
            frames += b.step(0.0)
        return frames
    got = count(_run_op(_ttype(1, s6=4), start_value))
    rows.append(("TPDO1 type 1, SYNC start value 4", "SYNC counters 1…6", f"{got} TPDO1",
                 "from the SYNC with counter 4 on: 3", got == 3))
    got = count(_run_op(lambda b: _invalidate(b), lambda b: b.step(1.0)))
    rows.append(("TPDO1 not valid (bit 31)", "1 s", f"{got} TPDO1",
                 "a PDO that does not exist is not sent: 0", got == 0))
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    table = object_rows() + rule_rows() + behaviour_rows()
    differ = [r for r in table if not r[-1]]
    lines = [
        "# CANopen conformance (generated by tools/conformance_canopen.py — do not edit)",
        "",
        "Every object of firmware-sim's accelerometer node read (and written where read-only), every",
        "CiA 301 v4.2 access rule of 1005h/1800h/1A00h with the mapping procedure and its abort codes,",
        "and what each transmission type puts on the bus; what the node answered; what CiA 301 says.",
        "",
        f"{len(table)} rows, {len(differ)} differ from CiA 301.",
        "",
        "| object / rule | action | firmware-sim answers | CiA 301 says | agrees |",
        "|---|---|---|---|---|",
    ]
    for what, action, got, want, ok in table:
        lines.append(f"| {what} | {action} | `{got}` | {want} | {'yes' if ok else '**no**'} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"{args.out}: {len(table)} rows, {len(differ)} differ from CiA 301")
    for row in differ:
        print("  differs:", row)
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
