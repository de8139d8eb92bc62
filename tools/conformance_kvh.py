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


USAGE_NOTE = ("the prompt's first word `USAGE` is firmware-sim's: the ICD's §7 breaks off at \"starting "
              "with the\" in every copy we found; §7.1 calls it \"a usage response\"")
NOT_READ = "§8, entry not read"
"""An §8 entry on a page we could not read (ICD p. 32–33, 35–41, 43, 45, 47–; see docs/PROTOCOLS.md §2.1)."""

ROWS = [
    Row("normal", "=config,1", "`CONFIG,1` (input is case-insensitive, replies upper case)",
        "§7 p. 24, §5.1 p. 13", _lines("CONFIG,1")),
    Row("normal", "?BIT", "a BIT message after the next data message", "§8.5 p. 31", None,
        note="no reply to the line itself: the BIT message follows the next data message (§8.5); "
        "tests/test_kvh_conformance.py reads it off a pty"),
    Row("normal", "?BIT,2", "extended BIT, 2 in Normal mode, after the next data message",
        "tech. manual p. 24, §5.3 p. 19", None, note="as ?BIT: it follows the next data message"),
    Row("normal", "?DR", "ignored: \"most commands are not recognized in Normal Mode\"",
        "§5.1 p. 13, §7 p. 24", None),
    Row("normal", "?LOGS", "ignored: `?logs` is a Configuration mode command", "tech. manual p. 24", None),
    Row("normal", "=FOO", "ignored (invalid commands are ignored in Normal Mode)", "§7 p. 24", None),
    Row("config", "=FOO", "`INVALID,` + echo of the input", "§7 p. 24", _lines("INVALID,=FOO")),
    Row("config", "?FOO", "`INVALID,` + echo of the input", "§7 p. 24", _lines("INVALID,?FOO")),
    Row("config", "=AXES,1,0,0,0,1,0,0,0,1", f"`{AXES_IDENTITY}` (the manual's example)", "§8.1.3 p. 30",
        _lines(AXES_IDENTITY)),
    Row("config", "?AXES", "`AXES,` + the 9 matrix elements", "§8.2.3 p. 30", _lines(AXES_IDENTITY)),
    Row("config", "=AXES,1,0", "a usage prompt (9 values needed)", "§7 p. 24, §7.1 p. 25", _usage("AXES"),
        note=USAGE_NOTE),
    Row("config", "=BAUD,921600", "`BAUD,921600`", "§8.3.3 p. 30", _lines("BAUD,921600"),
        note="a pty has no baud rate: the line speed does not change"),
    Row("config", "?BAUD", "`BAUD,921600` (the default)", "§8.4.3 p. 31", _lines("BAUD,921600")),
    Row("config", "=BAUD,1234", "a usage prompt (not one of §8.3.2's values)", "§7 p. 24, §8.3.2 p. 30",
        _usage("BAUD"), note=USAGE_NOTE),
    Row("config", "?BIT", "the extended BIT message, healthy: `FE 81 00 AA 7F 7F 7F 7F 7F 7F 23`",
        "§8.5 p. 31, Table 5-11 p. 19; tech. manual p. 25", HEALTHY_BIT),
    Row("config", "?BIT,2", "header `FE 81 00 AB`, 8 data bytes, checksum = sum of the bytes mod 256 "
        "(Table 5-11); the example `FE 81 00 AB 7F 7F 7F 7F 7F 7F 37 7F DA` (§5.3.2) follows that rule",
        "Table 5-11 p. 19, §5.3.2 p. 22", bytes.fromhex("FE 81 00 AB") + bytes([0x7F] * 8) + bytes([0x22])),
    Row("config", "?LOGS", "`Start of log entries!`, per entry `Log n:` / `Source - …` / `Format - BIT "
        "Status` / `Data - 0x…` (8 bytes), `End of log entries!`", "§8.25.3 p. 46",
        lambda r: r.startswith(b"Start of log entries!\r\nLog 1:\r\nSource - ?BIT\r\nFormat - BIT Status"
                               b"\r\nData - 0x7F7F7F7F7F7F7F7F\r\n")
        and r.endswith(b"End of log entries!\r\n"),
        note="the sources firmware-sim logs: `Start up`, `?BIT` (the manual's two), `?BIT,2` (its choice)"),
    Row("config", "=CONFIG,1", "`CONFIG,1`", "§7 p. 24, §3.3 p. 10", _lines("CONFIG,1")),
    Row("config", "?CONFIG", "`CONFIG,1`", "§7 p. 24", _lines("CONFIG,1")),
    Row("config", "=CONFIG,2", "a usage prompt", "§7 p. 24", _usage("CONFIG"), note=USAGE_NOTE),
    Row("config", "=DR,100", "`DR,100`", f"§7 p. 24, {NOT_READ}", _lines("DR,100")),
    Row("config", "?DR", "`DR,100`", f"§7 p. 24, {NOT_READ}", _lines("DR,100")),
    Row("config", "=DR,333", "a usage prompt (not a permitted rate)", "§7 p. 24", _usage("DR"),
        note=USAGE_NOTE),
    Row("config", "=DR,100.0", "\"integer type values, when received as float types, will typically be "
        "rejected with a usage response\"", "§7.1 p. 25", _usage("DR"), note=USAGE_NOTE),
    Row("config", "=DR,5000", "`DR,5000`", f"§7 p. 24, {NOT_READ}", _lines("DR,5000"),
        note="the pty carries 5000 Hz; a 921600-baud line would not (tech. manual p. 24: 4147200 Bd)"),
    Row("config", "=DR,1000", "`DR,1000`", f"§7 p. 24, {NOT_READ}", _lines("DR,1000")),
    Row("config", "=ECHO", "`ECHO,1` (the counter, incremented)", "§8.10 p. 34", _lines("ECHO,1")),
    Row("config", "=ECHO,5", "`ECHO,5` (set)", "§8.10.2 p. 34", _lines("ECHO,5")),
    Row("config", "?ECHO", "`ECHO,6` (identical to =ECHO)", "§8.11 p. 34", _lines("ECHO,6")),
    Row("config", "=ECHO,Reset", "`ECHO,0`", "§8.10.2 p. 34", _lines("ECHO,0")),
    Row("config", "?FILTTYPE,A", "`FILTTYPE,A,CHEBY` (the manual's example)", "§8.17.3 p. 44",
        _lines("FILTTYPE,A,CHEBY")),
    Row("config", "=FILTTYPE,G,AVE", "`FILTTYPE,G,AVE`", NOT_READ, _lines("FILTTYPE,G,AVE"),
        note="kept and reported; firmware-sim's sensor models have no output filter to change"),
    Row("config", "?FILTTYPE,G", "`FILTTYPE,G,AVE`", "§8.17.3 p. 44", _lines("FILTTYPE,G,AVE")),
    Row("config", "=FILTTYPE,X,AVE", "a usage prompt", "§7 p. 24", _usage("FILTTYPE"), note=USAGE_NOTE),
    Row("config", "=HELP", "the list of commands and their descriptions", "§8.18.3 p. 44",
        _help_lines(len(kvh.COMMANDS)), differs="the list's wording is firmware-sim's own"),
    Row("config", "?HELP", "identical to =HELP", "§8.19 p. 44", _help_lines(len(kvh.COMMANDS)),
        differs="the list's wording is firmware-sim's own"),
    Row("config", "=HELP,DR", "help on one command", "§8.18.2 p. 44", _help_lines(2),
        differs="the wording is firmware-sim's own"),
    Row("config", "?IS", "`IS,` + the serial number (a text string, typically numeric)", "§8.20.3 p. 44",
        lambda r: r.startswith(b"IS,") and r[3:-2].isdigit()),
    Row("config", "=MSYNC,EXT", "`MSYNC,EXT`; both output filters become the Averager", "Table 8-4 p. 42",
        _lines("MSYNC,EXT")),
    Row("config", "?FILTTYPE,A", "`FILTTYPE,A,AVE` (\"confirms the Averager type is active\")",
        "Table 8-4 p. 42", _lines("FILTTYPE,A,AVE")),
    Row("config", "=MSYNC,IMU", "`MSYNC,IMU`", NOT_READ, _lines("MSYNC,IMU")),
    Row("config", "?MSYNC", "`MSYNC,IMU` (the default)", NOT_READ, _lines("MSYNC,IMU"),
        note="=MSYNC,EXT is accepted; with no MSYNC input in the simulator the unit then sends no data"),
    Row("config", "=ROTFMT,RATE", "`ROTFMT,RATE`", f"§7 p. 24, {NOT_READ}", _lines("ROTFMT,RATE")),
    Row("config", "?ROTFMT", "`ROTFMT,RATE`", f"§7 p. 24, {NOT_READ}", _lines("ROTFMT,RATE")),
    Row("config", "=ROTFMT,FOO", "a usage prompt", "§7 p. 24", _usage("ROTFMT"), note=USAGE_NOTE),
    Row("config", "=ROTUNITS,DEG", "`ROTUNITS,DEG`", f"§7 p. 24, {NOT_READ}", _lines("ROTUNITS,DEG")),
    Row("config", "?ROTUNITS", "`ROTUNITS,DEG`", f"§7 p. 24, {NOT_READ}", _lines("ROTUNITS,DEG")),
    Row("config", "=TEMPUNITS,F", "`TEMPUNITS,F`; the temperature field in °C, 1/100 °C, °F or 1/100 °F",
        "Table 5-2 p. 14, Table 5-7 note p. 16", _lines("TEMPUNITS,F"),
        differs="°C and °F only: the ICD names a \"100ths of degree configuration of the =TEMPUNITS "
        "command\" (Table 5-7 note) but its =TEMPUNITS entry, with the parameter words, is on a page we "
        "could not read; C and F themselves are firmware-sim's words"),
    Row("config", "?TEMPUNITS", "`TEMPUNITS,F`", f"§7 p. 24, {NOT_READ}", _lines("TEMPUNITS,F")),
    Row("config", "=RSTCFG", "`RSTCFG`; factory configuration back, \"baud rate will not change for RSTCFG\"",
        "ICD p. 56 note 1", _lines("RSTCFG")),
    Row("config", "?ROTFMT", "`ROTFMT,DELTA` (the default, after =RSTCFG)", "Table 5-10 p. 18 (default: "
        "delta radians)", _lines("ROTFMT,DELTA")),
    Row("config", "=RESTART", "`RESTART`, then the unit starts again: the power-up BIT message",
        f"§5.1 p. 13, {NOT_READ}", _lines("RESTART") + HEALTHY_BIT),
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
        "that serves the pty); do not edit by hand. Reference: KVH \"1775 IMU Technical Manual\" 54-0938",
        "(\"tech. manual\", its own page numbers) and its Appendix C, the ICD 56-0298 Rev. B (§ and \"p. n\"",
        "= its \"Page n of 77\"): §7 \"Commands and Queries\" (rules), §8 (one entry per command), §3.3",
        "and §5.1 (modes), §3.4, §5.1 and §5.3 (BIT). Read at easymanua.ls/kvh-industries/1775-imu; ICD",
        "pages 32–33, 35–41, 43, 45 and 47–55 (Table 7-1, most of §8) were not in any copy we found:",
        "rows citing \"§8, entry not read\" rest on §7's general rules and on the previous copy's usage",
        "lines, not on the entry itself. Rows run in order on one unit, so state carries (`=DR,100` then",
        "`?DR`). Replies end in CR LF. \"same\": firmware-sim answers what the manual says (a note: what",
        "the simulator cannot act on, or what it had to choose); \"differs\": where its answer departs",
        "from the manual, and why.",
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
        "same-bytes tests). The usage prompt is `USAGE,` and the command's usage line: the ICD (§7 p. 24)",
        "says a bad parameter to a known keyword gets \"a prompt for the user starting with the …\" and",
        "the page ends there; §7.1 (p. 25) calls it \"a usage response\". The word `USAGE` and the rest",
        "of the line are firmware-sim's. Normal Mode answers `=CONFIG` and `?BIT` (with `?BIT,2`): the",
        "ICD's list of the permitted commands (Table 7-1) is on a page we could not read; §5.1 gives",
        "\"=config,1 or ?bit\" as examples and the technical manual names `?bit,2` in Normal mode.",
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
