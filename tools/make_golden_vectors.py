"""Write tests/golden/vectors.json: byte vectors taken from ../shared/PROTOCOLS.md.

This generator is a third, deliberately dumb implementation of each format, used once to
write the golden file that both `northfinder` (drivers) and `firmware_sim` (devices) are
tested against. The CRC here is not computed with either side's code: CRC-32/MPEG-2 is
obtained from zlib's reflected CRC-32 by reflecting every input byte and the result and
undoing the final xor (CRC-32/MPEG-2 = CRC-32 with refin=refout=False, xorout=0).

Run: python tools/make_golden_vectors.py  (rewrites the file; the test suite checks it is
unchanged by comparing with this script's output).
"""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

OUT = Path(__file__).resolve().parent.parent / "tests" / "golden" / "vectors.json"


def _reflect(value: int, width: int) -> int:
    out = 0
    for i in range(width):
        if value >> i & 1:
            out |= 1 << (width - 1 - i)
    return out


def crc32_mpeg2_via_zlib(data: bytes) -> int:
    """CRC-32/MPEG-2 through zlib: reflect bytes in, reflect the register out."""
    reflected = bytes(_reflect(b, 8) for b in data)
    # zlib: init 0xFFFFFFFF, reflected, xorout 0xFFFFFFFF -> undo the xorout, reflect back.
    return _reflect(zlib.crc32(reflected) ^ 0xFFFFFFFF, 32)


def kvh_message(gyro, accel, status, seq, temp_c) -> bytes:
    body = b"\xfe\x81\xff\x55" + struct.pack(">3f3fBBh", *gyro, *accel, status, seq, temp_c)
    return body + struct.pack(">I", crc32_mpeg2_via_zlib(body))


def nmea(body: str) -> str:
    checksum = 0
    for ch in body.encode("ascii"):
        checksum ^= ch
    return f"${body}*{checksum:02X}\r\n"


def _sdo(cmd: int, index: int, sub: int, data: bytes = b"") -> str:
    """One SDO payload (PROTOCOLS.md §3.1): command, index LE, sub-index, 4 data bytes."""
    return (struct.pack("<BHB", cmd, index, sub) + data.ljust(4, b"\0")).hex()


def _abort(index: int, sub: int, code: int) -> str:
    return _sdo(0x80, index, sub, struct.pack("<I", code))


def _segment(cmd: int, data: bytes = b"") -> str:
    return (bytes((cmd,)) + data.ljust(7, b"\0")).hex()


def sdo_exchanges() -> list[dict]:
    """SDO request/response pairs with the reference node (defaults of the §3.1 table), in
    order; `state` is the node's NMT state, `setup` exchanges come first and succeed."""
    name = b"NF-ACC3 accelerometer"  # 21 bytes: three 7-byte segments
    up = 0x40
    return [
        {
            "name": "upload 1018:1 vendor ID, expedited 4 bytes",
            "index": 0x1018,
            "sub": 1,
            "value": "e2040000",
            "steps": [
                {"request": _sdo(up, 0x1018, 1), "response": _sdo(0x43, 0x1018, 1, struct.pack("<I", 0x4E2))}
            ],
        },
        {
            "name": "upload 2100:0 sample rate, expedited 2 bytes",
            "index": 0x2100,
            "sub": 0,
            "value": "6400",
            "steps": [
                {"request": _sdo(up, 0x2100, 0), "response": _sdo(0x4B, 0x2100, 0, struct.pack("<H", 100))}
            ],
        },
        {
            "name": "upload 1a00:0 TPDO1 mapping count, expedited 1 byte",
            "index": 0x1A00,
            "sub": 0,
            "value": "02",
            "steps": [{"request": _sdo(up, 0x1A00, 0), "response": _sdo(0x4F, 0x1A00, 0, b"\x02")}],
        },
        {
            "name": "upload 1008:0 device name, segmented",
            "index": 0x1008,
            "sub": 0,
            "value": name.hex(),
            "steps": [
                {
                    "request": _sdo(up, 0x1008, 0),
                    "response": _sdo(0x41, 0x1008, 0, struct.pack("<I", len(name))),
                },
                {"request": _segment(0x60), "response": _segment(0x00, name[0:7])},
                {"request": _segment(0x70), "response": _segment(0x10, name[7:14])},
                {"request": _segment(0x60), "response": _segment(0x01, name[14:21])},
            ],
        },
        {
            "name": "download 2100:0 = 50 Hz, expedited 2 bytes",
            "index": 0x2100,
            "sub": 0,
            "value": "3200",
            "steps": [
                {"request": _sdo(0x2B, 0x2100, 0, struct.pack("<H", 50)), "response": _sdo(0x60, 0x2100, 0)}
            ],
        },
        {
            "name": "download 1017:0 = 500 ms heartbeat",
            "index": 0x1017,
            "sub": 0,
            "value": "f401",
            "steps": [
                {"request": _sdo(0x2B, 0x1017, 0, struct.pack("<H", 500)), "response": _sdo(0x60, 0x1017, 0)}
            ],
        },
        {
            "name": "abort: object does not exist",
            "index": 0x2200,
            "sub": 0,
            "abort": 0x06020000,
            "steps": [{"request": _sdo(up, 0x2200, 0), "response": _abort(0x2200, 0, 0x06020000)}],
        },
        {
            "name": "abort: sub-index does not exist",
            "index": 0x1018,
            "sub": 9,
            "abort": 0x06090011,
            "steps": [{"request": _sdo(up, 0x1018, 9), "response": _abort(0x1018, 9, 0x06090011)}],
        },
        {
            "name": "abort: write to a read-only object",
            "index": 0x1018,
            "sub": 1,
            "value": "01000000",
            "abort": 0x06010002,
            "steps": [
                {
                    "request": _sdo(0x23, 0x1018, 1, struct.pack("<I", 1)),
                    "response": _abort(0x1018, 1, 0x06010002),
                }
            ],
        },
        {
            "name": "abort: length mismatch (u16 written with 4 bytes)",
            "index": 0x2100,
            "sub": 0,
            "value": "32000000",
            "abort": 0x06070010,
            "steps": [
                {
                    "request": _sdo(0x23, 0x2100, 0, struct.pack("<I", 50)),
                    "response": _abort(0x2100, 0, 0x06070010),
                }
            ],
        },
        {
            "name": "abort: value range exceeded (rate 0 Hz)",
            "index": 0x2100,
            "sub": 0,
            "value": "0000",
            "abort": 0x06090030,
            "steps": [{"request": _sdo(0x2B, 0x2100, 0, b"\0\0"), "response": _abort(0x2100, 0, 0x06090030)}],
        },
        {
            "name": "abort: rate written while operational",
            "state": "operational",
            "index": 0x2100,
            "sub": 0,
            "value": "1900",
            "abort": 0x08000022,
            "steps": [
                {
                    "request": _sdo(0x2B, 0x2100, 0, struct.pack("<H", 25)),
                    "response": _abort(0x2100, 0, 0x08000022),
                }
            ],
        },
        {
            "name": "abort: mapping of 96 bits (CiA 301 §7.5.2.38 procedure: invalidate, count 0, entry)",
            "index": 0x1A00,
            "sub": 0,
            "value": "03",
            "abort": 0x06040042,
            "setup": [
                {
                    "request": _sdo(0x23, 0x1800, 1, struct.pack("<I", 0x80000190)),
                    "response": _sdo(0x60, 0x1800, 1),
                },
                {"request": _sdo(0x2F, 0x1A00, 0, b"\0"), "response": _sdo(0x60, 0x1A00, 0)},
                {
                    "request": _sdo(0x23, 0x1A00, 3, struct.pack("<I", 0x20000320)),
                    "response": _sdo(0x60, 0x1A00, 3),
                },
            ],
            "steps": [{"request": _sdo(0x2F, 0x1A00, 0, b"\x03"), "response": _abort(0x1A00, 0, 0x06040042)}],
        },
    ]


def build() -> dict:
    assert crc32_mpeg2_via_zlib(b"123456789") == 0x0376E6E7
    kvh = [
        {
            "name": "three-axis gyro + accel, delta angles in rad",
            "gyro": [1.0e-5, -2.0e-5, 3.0e-5],
            "accel_g": [0.01, -0.02, 1.0],
            "status": 0x77,
            "sequence": 42,
            "temperature_c": 25,
        },
        {
            "name": "single-axis gyro (y only), accel fields zero and invalid",
            "gyro": [0.0, 7.2921150e-8, 0.0],
            "accel_g": [0.0, 0.0, 0.0],
            "status": 0x02,
            "sequence": 127,
            "temperature_c": -5,
        },
        {
            "name": "three-axis gyro only, rates in deg/s",
            "gyro": [0.5, -0.25, 90.0],
            "accel_g": [0.0, 0.0, 0.0],
            "status": 0x07,
            "sequence": 0,
            "temperature_c": 40,
        },
    ]
    for v in kvh:
        msg = kvh_message(v["gyro"], v["accel_g"], v["status"], v["sequence"], v["temperature_c"])
        v["hex"] = msg.hex()
        # the float32 values actually on the wire, for exact comparisons after decoding
        v["gyro_f32"] = list(struct.unpack(">3f", msg[4:16]))
        v["accel_f32"] = list(struct.unpack(">3f", msg[16:28]))
        v["crc"] = f"0x{struct.unpack('>I', msg[32:36])[0]:08X}"

    smc100 = {
        "replies": [
            {"hex": b"1TS00000A\r\n".hex(), "address": 1, "errors": 0x0000, "state": 0x0A},
            {"hex": b"1TS000032\r\n".hex(), "address": 1, "errors": 0x0000, "state": 0x32},
            {"hex": b"1TS000028\r\n".hex(), "address": 1, "errors": 0x0000, "state": 0x28},
            {"hex": b"1TS002033\r\n".hex(), "address": 1, "errors": 0x0020, "state": 0x33},
            {"hex": b"2TS00011E\r\n".hex(), "address": 2, "errors": 0x0001, "state": 0x1E},
            {"hex": b"1TEH\r\n".hex(), "address": 1, "error_letter": "H"},
            {"hex": b"1TE@\r\n".hex(), "address": 1, "error_letter": "@"},
            {"hex": b"1TP90.00010\r\n".hex(), "address": 1, "position": 90.0001},
            {"hex": b"1TP-12.5\r\n".hex(), "address": 1, "position": -12.5},
            {"hex": b"1SL-360\r\n".hex(), "address": 1, "soft_limit": -360.0},
            {"hex": b"1SR360\r\n".hex(), "address": 1, "soft_limit": 360.0},
        ],
        "commands": [
            {"hex": b"1PA90.000\r\n".hex(), "address": 1, "command": "PA", "value": 90.0},
            {"hex": b"1PA90\r\n".hex(), "address": 1, "command": "PA", "value": 90.0},
            {"hex": b"1PR-45.5\r\n".hex(), "address": 1, "command": "PR", "value": -45.5},
            {"hex": b"1TP?\r\n".hex(), "address": 1, "command": "TP", "value": None, "query": True},
            {"hex": b"1TP\r\n".hex(), "address": 1, "command": "TP", "value": None, "query": False},
            {"hex": b"1OR\r\n".hex(), "address": 1, "command": "OR", "value": None, "query": False},
            {"hex": b"12TS\r\n".hex(), "address": 12, "command": "TS", "value": None, "query": False},
        ],
        # A session on a freshly reset stage, as the device must answer it. `null` reply: the
        # command sends nothing. `wait_ready` means: poll TS until the state is READY.
        "exchange": [
            {"send": "1TS", "reply": "1TS00000A"},
            {"send": "1PA90", "reply": None},
            {"send": "1TE", "reply": "1TEH"},
            {"send": "1TE", "reply": "1TE@"},
            {"send": "1OR", "reply": None},
            {"send": "1TE", "reply": "1TE@"},
            {"wait_ready": True, "state": 0x32},
            {"send": "1PA90", "reply": None},
            {"send": "1TE", "reply": "1TE@"},
            {"wait_ready": True, "state": 0x33},
            {"send": "1TP", "reply_position_near": 90.0},
            {"send": "1XX", "reply": None},
            {"send": "1TE", "reply": "1TEA"},
            {"send": "1PA400", "reply": None},
            {"send": "1TE", "reply": "1TEG"},
        ],
    }

    node = 0x10
    can = [
        {"name": "NMT start node 0x10", "id": 0x000, "data": "0110"},
        {"name": "NMT start all nodes", "id": 0x000, "data": "0100"},
        {"name": "NMT stop node 0x10", "id": 0x000, "data": "0210"},
        {"name": "heartbeat boot-up", "id": 0x700 + node, "data": "00", "state": 0x00},
        {"name": "heartbeat operational", "id": 0x700 + node, "data": "05", "state": 0x05},
        {"name": "heartbeat pre-operational", "id": 0x700 + node, "data": "7f", "state": 0x7F},
        {
            "name": "TPDO1 x=+1000 ug, y=-2000 ug",
            "id": 0x180 + node,
            "data": struct.pack("<ii", 1000, -2000).hex(),
            "accel_x_ug": 1000,
            "accel_y_ug": -2000,
        },
        {
            "name": "TPDO2 z=1 g, 25.12 C, counter 7, xyz valid",
            "id": 0x280 + node,
            "data": struct.pack("<ihBB", 1_000_000, 2512, 7, 0x07).hex(),
            "accel_z_ug": 1_000_000,
            "temperature_centi_c": 2512,
            "counter": 7,
            "status": 0x07,
        },
        {
            "name": "TPDO2 z=-0.5 g, -3.5 C, counter 255, over-range",
            "id": 0x280 + node,
            "data": struct.pack("<ihBB", -500_000, -350, 255, 0x87).hex(),
            "accel_z_ug": -500_000,
            "temperature_centi_c": -350,
            "counter": 255,
            "status": 0x87,
        },
        {
            "name": "EMCY heartbeat/life guard",
            "id": 0x080 + node,
            "data": struct.pack("<HB5s", 0x8130, 0x01, b"\0" * 5).hex(),
            "error_code": 0x8130,
            "error_register": 0x01,
        },
    ]

    sdo = sdo_exchanges()

    def slcan_frame(can_id: int, data_hex: str) -> str:
        data = bytes.fromhex(data_hex)
        return f"t{can_id:03X}{len(data):d}{data.hex().upper()}\r"

    slcan = {
        "frames": [
            {"id": f["id"], "data": f["data"], "extended": False, "line": slcan_frame(f["id"], f["data"])}
            for f in can
        ]
        + [
            {
                "id": 0x1ABCDEF0,
                "data": "1122334455667788",
                "extended": True,
                "line": "T1ABCDEF081122334455667788\r",
            },
            {"id": 0x123, "data": "", "extended": False, "line": "t1230\r"},
        ],
        "commands": [
            {"send": "S6\r", "reply": "\r"},
            {"send": "O\r", "reply": "\r"},
            {"send": "C\r", "reply": "\r"},
            {"send": "V\r", "reply": "V1013\r"},
            {"send": "N\r", "reply": "NA123\r"},
            {"send": "S9\r", "reply": "\x07"},
            {"send": "Z\r", "reply": "\x07"},
        ],
    }

    gga = "GNGGA,123519.00,4007.0380000,N,11631.0000000,E,1,12,0.8,45.400,M,-8.2,M,,"
    rmc = "GNRMC,123519.00,A,4007.0380000,N,11631.0000000,E,10.500,84.40,221126,,,A"
    vtg = "GNVTG,84.40,T,,M,10.500,N,19.446,K,A"
    nmea_vectors = [
        {
            "sentence": nmea(gga),
            "type": "GGA",
            "lat_deg": 40 + 7.038 / 60,
            "lon_deg": 116 + 31.0 / 60,
            "alt_m": 45.4,
            "fix_quality": 1,
            "num_sv": 12,
        },
        {"sentence": nmea(rmc), "type": "RMC", "speed_knots": 10.5, "course_deg": 84.4},
        {"sentence": nmea(vtg), "type": "VTG", "course_deg": 84.4, "speed_kmh": 19.446},
        {
            "sentence": nmea("GNGGA,000000.00,0000.0000000,S,00000.0000000,W,0,00,99.9,0.000,M,0.0,M,,"),
            "type": "GGA",
            "fix_quality": 0,
            "note": "no fix",
        },
    ]
    bad_nmea = [
        nmea(gga)[:-5] + "00\r\n",  # wrong checksum
        nmea(gga)[:30] + "\r\n",  # truncated
        "$GNGGA,123519.00\r\n",  # no checksum at all
    ]

    return {
        "source": "../shared/PROTOCOLS.md; generated by tools/make_golden_vectors.py",
        "crc32_mpeg2": [
            {"ascii": "123456789", "crc": "0x0376E6E7"},
            {"ascii": "", "crc": f"0x{crc32_mpeg2_via_zlib(b''):08X}"},
            {"hex": "fe81ff55", "crc": f"0x{crc32_mpeg2_via_zlib(bytes.fromhex('fe81ff55')):08X}"},
        ],
        "kvh_format_a": kvh,
        "smc100": smc100,
        "canopen": {"node_id": node, "frames": can},
        "canopen_sdo": {
            "node_id": node,
            "request_id": 0x600 + node,
            "response_id": 0x580 + node,
            "exchanges": sdo,
        },
        "slcan": slcan,
        "nmea": {"good": nmea_vectors, "bad": bad_nmea},
    }


MODELS_OUT = OUT.parent / "models.json"


def _apt_vectors() -> list[dict]:
    """Thorlabs APT: the byte examples printed in the Host-Controller Communications Protocol,
    Issue 28 (21 Sep 2021), page by page. HW_GET_INFO's example elides its 60 internal-use bytes;
    they are zero here, and its trailing bytes give HW version 1, mod state 0, 1 channel."""
    info = (struct.pack("<i8sH4B", 94000009, b"ION001 \0", 44, 2, 1, 0x39, 0) + bytes(60)
            + struct.pack("<HHH", 1, 0, 1))
    return [
        {"name": "HW_REQ_INFO to controller #1", "page": 51, "hex": "050000001101"},
        {"name": "MOD_SET_CHANENABLESTATE enable channel in bay 2", "page": 46, "hex": "100201012201",
         "channel": 1, "enable": True, "dest": 0x22},
        {"name": "MOT_MOVE_HOME channel in bay 2", "page": 79, "hex": "430401002201", "channel": 1,
         "dest": 0x22},
        {"name": "MOT_MOVE_HOMED from bay 2", "page": 79, "hex": "440401000122", "channel": 1,
         "source": 0x22},
        {"name": "MOT_MOVE_ABSOLUTE chan 2 to 10 mm (200000 counts)", "page": 84,
         "hex": "53040600a2010100400d0300", "channel": 1, "position": 200000, "dest": 0x22},
        {"name": "MOT_ACK_DCSTATUSUPDATE", "page": 129, "hex": "920400002101", "dest": 0x21},
        {"name": "HW_GET_INFO from bay 2 (ION001)", "page": 52,
         "hex": (struct.pack("<HHBB", 0x0006, 84, 0x81, 0x22) + info).hex(),
         "serial_number": 94000009, "model": "ION001", "hw_type": 44, "firmware": [0x39, 1, 2],
         "hw_version": 1, "mod_state": 0, "channels": 1},
    ]


def _stim_datagram(ident: int, words: list[int | bytes], counter: int, latency_us: int) -> bytes:
    """A normal-mode datagram by TS1524 Table 5-20: 24-bit words and STATUS bytes in order."""
    body = bytes([ident])
    for w in words:
        body += w if isinstance(w, bytes) else (w & 0xFFFFFF).to_bytes(3, "big")
    body += bytes([counter]) + latency_us.to_bytes(2, "big")
    padded = body + bytes(-len(body) % 4)  # Table 5-22 dummies
    return body + crc32_mpeg2_via_zlib(padded).to_bytes(4, "big")


def _stim_vectors() -> dict:
    """STIM300 (TS1524 rev.31): the sheet prints no datagram bytes, so these are made here from
    Table 5-20/5-21 (layout), §5.5.7 (CRC, dummies of Table 5-22) and §7.5.2.2 (scaling)."""
    s0 = b"\x00"
    gyro = [1 << 14, -(1 << 13), 123]  # +1 °/s, −0.5 °/s, 123/2^14 °/s (rate) or /2^21 ° (increment)
    acc = [0, 1 << 19, -(1 << 18)]  # 10 g range: 0, +1 g, −0.5 g
    incl = [1 << 22, 0, -(1 << 20)]  # +1 g, 0, −0.25 g
    v93 = _stim_datagram(0x93, [*gyro, s0, *acc, s0, *incl, s0], 4, 500)
    v90 = _stim_datagram(0x90, [*gyro, b"\x41"], 255, 0x1234)  # start-up + X channel flagged
    serial = bytes([0xB5, ord("N"), 0x25, 0x58, 0x24, 0x05, 0x00, 0x20, 0x02]) + bytes(7)
    serial += crc32_mpeg2_via_zlib(serial).to_bytes(4, "big")
    return {
        "check": {"ascii": "123456789", "crc": "0376E6E7"},
        "datagrams": [
            {"id": 0x93, "hex": v93.hex(), "gyro_raw": gyro, "acc_raw": acc, "incl_raw": incl,
             "status": [0, 0, 0], "counter": 4, "latency_us": 500, "length": 38},
            {"id": 0x90, "hex": v90.hex(), "gyro_raw": gyro, "status": [0x41], "counter": 255,
             "latency_us": 0x1234, "length": 18},
        ],
        "serial_datagram": {"hex": serial.hex(), "serial": "N25582405002002"},
        "lengths": {"0x90": 18, "0x91": 28, "0x92": 28, "0x93": 38, "0x94": 25, "0xA5": 42, "0xA6": 42,
                    "0xA7": 59, "0xF0": 22, "0xF7": 63},
        "dummies": {"0x90": 2, "0x91": 0, "0x93": 2, "0x94": 3, "0xA5": 2, "0xA7": 1, "0xF4": 3, "0xF7": 1},
    }


def _cia410_vectors() -> dict:
    """CiA 410 (DS 410 v1.2): TPDO1 of the default mapping (0x6010, 0x6020, INTEGER16 LE) and the
    CiA 301 expedited SDO upload of 0x6000 (resolution 1 = 0.001°)."""
    return {
        "tpdo1": [
            {"long": 1000, "lateral": -2000, "hex": struct.pack("<hh", 1000, -2000).hex()},
            {"long": -32768, "lateral": 32767, "hex": struct.pack("<hh", -32768, 32767).hex()},
        ],
        "sdo_upload_resolution": {"request": "4000600000000000", "response": "4b00600001000000"},
        "inversion": {"physical": 1000, "operating": 1, "shown": -1000},
    }


def build_models() -> dict:
    return {
        "source": "second models (issue 24): Thorlabs APT Issue 28, STIM300 TS1524 rev.31, CiA DS 410 v1.2",
        "apt": _apt_vectors(),
        "stim": _stim_vectors(),
        "cia410": _cia410_vectors(),
    }


def main() -> None:
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(build(), indent=1) + "\n")
    print(f"wrote {OUT}")
    MODELS_OUT.write_text(json.dumps(build_models(), indent=1) + "\n")
    print(f"wrote {MODELS_OUT}")


if __name__ == "__main__":
    main()
