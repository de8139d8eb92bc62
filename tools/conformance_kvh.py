"""The KVH 1750/1775 conformance table, generated from firmware-sim itself.

Every command and query of the 1775 technical manual's command table (§7 "Commands and Queries",
§8 one entry per command) and the general rules of §7 (echoes, INVALID, usage prompts, Normal vs
Configuration Mode) and §3.4/§5.3 (the power-up BIT message): the input sent, what firmware-sim's
KVH unit answers (its `KvhImu.answer`, the code that serves the pty), what the manual says, and
whether the two agree. Rows that differ carry the reason.

Run: ``python tools/conformance_kvh.py [--out docs/conformance/kvh.md]`` (``--check`` exits 1 when
the file on disk is not what the simulator gives now).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run from a checkout without installing

from firmware_sim.devices import kvh  # noqa: E402

HEALTHY_BIT = bytes.fromhex("FE 81 00 AA 7F 7F 7F 7F 7F 7F 23")
AXES_IDENTITY = "AXES," + ",".join(f"{v:+.6E}" for v in (1, 0, 0, 0, 1, 0, 0, 0, 1))


@dataclass(frozen=True)
class Row:
    mode: str  # "config" or "normal": the mode the unit is in when the line arrives
    line: str  # what the host sends (without the line end)
    manual: str  # what the manual says the unit answers
    section: str
    expected: bytes | Callable[[bytes], bool] | None  # exact bytes, a predicate, or None = no reply
    differs: str = ""  # where firmware-sim's answer departs from the manual, and why (empty: it does not)
    note: str = ""  # the answer is the manual's, but the simulator cannot act on it fully


def _lines(*texts: str) -> bytes:
    return b"".join(t.encode("ascii") + kvh.EOL for t in texts)


def _usage(key: str) -> Callable[[bytes], bool]:
    return lambda reply: reply.startswith(b"USAGE,=" + key.encode("ascii"))


def _help_lines(n: int) -> Callable[[bytes], bool]:
    return lambda reply: reply.count(kvh.EOL) == n


ROWS = [
    Row("normal", "=config,1", "`CONFIG,1` (input is case-insensitive, replies upper case)", "§7, §3.3",
        _lines("CONFIG,1")),
    Row("normal", "?BIT", "a BIT message after the next data message", "§8.5", None,
        note="no reply to the line itself: the BIT message follows the next data message (§8.5); "
        "tests/test_kvh_conformance.py reads it off a pty"),
    Row("normal", "?DR", "ignored: not permitted in Normal Mode", "§7, §3.3", None),
    Row("normal", "=FOO", "ignored (invalid commands are ignored in Normal Mode)", "§7", None),
    Row("config", "=FOO", "`INVALID,` + echo of the input", "§7", _lines("INVALID,=FOO")),
    Row("config", "?FOO", "`INVALID,` + echo of the input", "§7", _lines("INVALID,?FOO")),
    Row("config", "=AXES,1,0,0,0,1,0,0,0,1", f"`{AXES_IDENTITY}` (the manual's example)", "§8.1.3",
        _lines(AXES_IDENTITY)),
    Row("config", "?AXES", "`AXES,` + the 9 matrix elements", "§8.2.3", _lines(AXES_IDENTITY)),
    Row("config", "=AXES,1,0", "usage prompt (9 values needed)", "§7, §8.1", _usage("AXES")),
    Row("config", "=BAUD,921600", "`BAUD,921600`", "§8.3.3", _lines("BAUD,921600"),
        note="a pty has no baud rate: the line speed does not change"),
    Row("config", "?BAUD", "`BAUD,921600` (the default)", "§8.4.3", _lines("BAUD,921600")),
    Row("config", "=BAUD,1234", "usage prompt", "§7, §8.3.2", _usage("BAUD")),
    Row("config", "?BIT", "the extended BIT message, healthy: `FE 81 00 AA 7F 7F 7F 7F 7F 7F 23`",
        "§8.5, §5.3", HEALTHY_BIT),
    Row("config", "?BIT,2", "extended BIT, 2: header `FE 81 00 AB`, 8 data bytes, checksum; example "
        "`FE 81 00 AA 7F 7F 7F 7F 7F 7F 7F 7F 23`", "tech. manual \"Extended BIT, 2\"",
        bytes.fromhex("FE 81 00 AB") + bytes([0x7F] * 8) + bytes([0x22]),
        differs="the checksum: the manual's example ends in 23 after a 00 AA header; its own rule (the sum "
        "of the bytes, header included, mod 256) gives 22 for the 00 AB header it names, and "
        "firmware-sim follows the rule"),
    Row("config", "=CONFIG,1", "`CONFIG,1`", "§7, §3.3", _lines("CONFIG,1")),
    Row("config", "?CONFIG", "`CONFIG,1`", "§7", _lines("CONFIG,1")),
    Row("config", "=CONFIG,2", "usage prompt", "§7", _usage("CONFIG")),
    Row("config", "=DR,100", "`DR,100`", "§8.8.3", _lines("DR,100")),
    Row("config", "?DR", "`DR,100`", "§8.9.3", _lines("DR,100")),
    Row("config", "=DR,333", "usage prompt (not a permitted rate)", "§7, §8.8.2", _usage("DR")),
    Row("config", "=DR,5000", "`DR,5000`", "§8.8.3", _lines("DR,5000"),
        note="the pty carries 5000 Hz; a 921600-baud line would not (§9)"),
    Row("config", "=DR,1000", "`DR,1000`", "§8.8.3", _lines("DR,1000")),
    Row("config", "?FILTTYPE,A", "`FILTTYPE,A,CHEBY` (the manual's example)", "§8.17.3",
        _lines("FILTTYPE,A,CHEBY")),
    Row("config", "=FILTTYPE,G,AVE", "`FILTTYPE,G,AVE`", "§8.16", _lines("FILTTYPE,G,AVE"),
        note="kept and reported; firmware-sim's sensor models have no output filter to change"),
    Row("config", "?FILTTYPE,G", "`FILTTYPE,G,AVE`", "§8.17.3", _lines("FILTTYPE,G,AVE")),
    Row("config", "=FILTTYPE,X,AVE", "usage prompt", "§7", _usage("FILTTYPE")),
    Row("config", "=HELP", "the list of commands and their descriptions", "§8.18.3",
        _help_lines(len(kvh.COMMANDS)), differs="the list's wording is firmware-sim's own"),
    Row("config", "?HELP", "identical to =HELP", "§8.19", _help_lines(len(kvh.COMMANDS)),
        differs="the list's wording is firmware-sim's own"),
    Row("config", "=HELP,DR", "help on one command", "§8.18.2", _help_lines(2),
        differs="the wording is firmware-sim's own"),
    Row("config", "?IS", "`IS,` + the serial number (a text string, typically numeric)", "§8.20.3",
        lambda r: r.startswith(b"IS,") and r[3:-2].isdigit()),
    Row("config", "=MSYNC,IMU", "`MSYNC,IMU`", "§8", _lines("MSYNC,IMU")),
    Row("config", "?MSYNC", "`MSYNC,IMU` (the default)", "§8", _lines("MSYNC,IMU"),
        note="=MSYNC,EXT is accepted; with no MSYNC input in the simulator the unit then sends no data"),
    Row("config", "=ROTFMT,RATE", "`ROTFMT,RATE`", "§8", _lines("ROTFMT,RATE")),
    Row("config", "?ROTFMT", "`ROTFMT,RATE`", "§8", _lines("ROTFMT,RATE")),
    Row("config", "=ROTFMT,FOO", "usage prompt", "§7", _usage("ROTFMT")),
    Row("config", "=ROTUNITS,DEG", "`ROTUNITS,DEG`", "§8", _lines("ROTUNITS,DEG")),
    Row("config", "?ROTUNITS", "`ROTUNITS,DEG`", "§8", _lines("ROTUNITS,DEG")),
    Row("config", "=TEMPUNITS,F", "`TEMPUNITS,F`; the temperature field in °C, 1/100 °C, °F or 1/100 °F",
        "§8, Table 5-2", _lines("TEMPUNITS,F"),
        differs="°C and °F only: the 1/100 °C and 1/100 °F settings are not in firmware-sim (their "
        "parameter words are not in the copy of the manual we have)"),
    Row("config", "?TEMPUNITS", "`TEMPUNITS,F`", "§8", _lines("TEMPUNITS,F")),
    Row("config", "=RSTCFG", "`RSTCFG`; factory configuration back, baud rate kept", "§8, §9 note 1",
        _lines("RSTCFG")),
    Row("config", "?ROTFMT", "`ROTFMT,DELTA` (the default, after =RSTCFG)", "§8", _lines("ROTFMT,DELTA")),
    Row("config", "=RESTART", "`RESTART`, then the unit starts again: the power-up BIT message", "§8, §3.4",
        _lines("RESTART") + HEALTHY_BIT),
]
"""Rows in the order they are sent to one unit (state carries over: =DR,100 then ?DR)."""


def run_rows() -> list[tuple[Row, bytes]]:
    """Send every row's line to a fresh firmware-sim unit (no world: no data is produced)."""
    unit = kvh.KvhImu(world=None)
    try:
        out = []
        for row in ROWS:
            unit.config_mode = row.mode == "config"
            out.append((row, b"".join(unit.answer(row.line, 0.0))))
        return out
    finally:
        unit.close()


def _shown(reply: bytes) -> str:
    if not reply:
        return "no reply"
    cut = reply.find(b"\xfe\x81")
    if cut == 0:
        return "`" + reply.hex(" ").upper() + "`"
    if cut > 0:
        return _shown(reply[:cut]) + ", then " + _shown(reply[cut:])
    lines = reply.decode("ascii").split("\r\n")[:-1]
    if len(lines) > 3:
        return f"{len(lines)} lines, first `{lines[0]}`"
    return "<br>".join(f"`{ln}`" for ln in lines)


def _agrees(row: Row, reply: bytes) -> bool:
    if row.expected is None:
        return reply == b""
    if callable(row.expected):
        return bool(row.expected(reply))
    return reply == row.expected


def table() -> tuple[str, list[tuple[Row, bytes]]]:
    rows = run_rows()
    out = [
        "# KVH 1750/1775 conformance: firmware-sim against the manual",
        "",
        "Generated by `tools/conformance_kvh.py` from firmware-sim's KVH unit (`KvhImu.answer`, the code",
        "that serves the pty); do not edit by hand. Reference: KVH 1775 IMU technical manual / ICD",
        "(56-0298), §7 \"Commands and Queries\" (rules), §8 (one entry per command), §3.3 (modes), §3.4",
        "and §5.3 (BIT). Rows run in order on one unit, so state carries (`=DR,100` then `?DR`). Replies",
        "end in CR LF. \"same\": firmware-sim answers what the manual says (a note: what the simulator",
        "cannot act on); \"differs\": where its answer departs from the manual, and why.",
        "",
        "| # | mode | host sends | firmware-sim answers | the manual says | § | agrees |",
        "|---|---|---|---|---|---|---|",
    ]
    for k, (row, reply) in enumerate(rows, 1):
        if not _agrees(row, reply):
            verdict = "**not as tabulated** (a defect of firmware-sim or of this table)"
        elif row.differs:
            verdict = f"**differs**: {row.differs}"
        else:
            verdict = "same" + (f" (note: {row.note})" if row.note else "")
        out.append(f"| {k} | {row.mode} | `{row.line}` | {_shown(reply)} | {row.manual} | {row.section} "
                   f"| {verdict} |")
    out += [
        "",
        "Also (not a line sent): at power-up the unit sends the BIT message",
        "`FE 81 00 AA 7F 7F 7F 7F 7F 7F 23` before its first data message (§3.4). firmware-sim does so",
        "with `KvhImu(power_up_bit=True)` or the `imu-dialogue-rate` fault (which also sends it to each",
        "new client); it is off by default so that every scenario's byte stream stays what it was (the",
        "same-bytes tests). The usage prompt is `USAGE,` and the command's usage line: the manual (§7)",
        "says a bad parameter to a known keyword gets \"a prompt for the user starting with the …\";",
        "the copy available to us breaks off there, so that word is firmware-sim's choice.",
        "",
    ]
    return "\n".join(out), rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent.parent / "docs/conformance/kvh.md"))
    ap.add_argument("--check", action="store_true", help="exit 1 if --out differs from what is generated now")
    args = ap.parse_args()
    text, rows = table()
    path = Path(args.out)
    if args.check:
        same = path.exists() and path.read_text() == text
        print(f"{path}: {'up to date' if same else 'OUT OF DATE'}")
        return 0 if same else 1
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    broken = [k for k, (r, reply) in enumerate(rows, 1) if not _agrees(r, reply)]
    differs = [(k, r) for k, (r, _) in enumerate(rows, 1) if r.differs]
    noted = [(k, r) for k, (r, _) in enumerate(rows, 1) if r.note]
    print(f"{path}: {len(rows)} rows; {len(differs)} differ from the manual (each with its reason), "
          f"{len(noted)} same with a note, {len(broken)} not as tabulated")
    for k, r in differs:
        print(f"  differs, row {k} ({r.mode}) {r.line}: {r.differs}")
    for k, r in noted:
        print(f"  note, row {k} ({r.mode}) {r.line}: {r.note}")
    return 1 if broken else 0


if __name__ == "__main__":
    raise SystemExit(main())
