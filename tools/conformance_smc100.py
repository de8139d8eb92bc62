"""The SMC100 conformance table: every command of the user manual's command list, in its query
form and its set/execute form in each controller state, sent to firmware-sim's controller → what
it answers (reply lines and the TE letter read after) → what the manual says.

The manual's expectations are written here from the manual, independently of the simulator's
own tables: Newport "SMC100CC & SMC100PP … User's Manual" V3.0.x, EDH0206En2054 (06/23), §5.5
"Command Set" — the command list (p. 18) and each command's page (its Usage row: the states it
is accepted in; its range, errors, reply and example). The 09/18 edition (EDH0206En2051) has the
same Usage rows. Writes docs/conformance/smc100.md and prints the row count and every row that
differs; exit status 1 when any does.

    python tools/conformance_smc100.py [--out docs/conformance/smc100.md]
"""

from __future__ import annotations

import argparse
import re
import sys
from dataclasses import dataclass
from pathlib import Path

from firmware_sim.devices.smc100 import Smc100
from firmware_sim.physics.table import TableMotion

OUT = Path(__file__).resolve().parents[1] / "docs" / "conformance" / "smc100.md"

NR, CF, DI, RD = "NOT REFERENCED", "CONFIGURATION", "DISABLE", "READY"
HO, MV, JG = "HOMING", "MOVING", "JOGGING"
STATES = (NR, CF, DI, RD, HO, MV, JG)
LETTER = {NR: "H", CF: "I", DI: "J", RD: "K", HO: "L", MV: "M", JG: "D"}
"""The TE table (p. 59) has a letter per state; JOGGING has none of its own: D "Command not allowed"."""
ANY = frozenset(STATES)
NOT_JOGGING = ANY - {JG}
WORK = frozenset({CF, DI, RD})
LOOP = frozenset({CF, DI})
MOTION = frozenset({HO, MV})  # the command list's "Motion" column: HOMING and MOVING

NUM = r"-?\d+(\.\d+)?"


@dataclass(frozen=True)
class Manual:
    """One command as the manual gives it: its page, a set/execute example, the states of its
    Usage row, the query form's reply (regex), or a letter for every state (X: not for CC)."""

    title: str
    page: str
    set_text: str | None
    allowed: frozenset[str] = frozenset({CF})
    query_reply: str | None = None
    always: str | None = None  # X: "Not for CC" in the command list
    set_reply: str | None = None  # a command whose execute form answers (PT, TB, …) where allowed
    query_text: str | None = None  # when the query is not `1XX?` (QI: `1QIL?`)


def _p(title: str, page: str, example: str, allowed: frozenset[str] = frozenset({CF}),
       code: str = "") -> Manual:
    return Manual(title, page, example, allowed, rf"1{code}{NUM}")


MANUAL: dict[str, Manual] = {
    "AC": _p("Set/Get acceleration", "20", "1AC500", WORK, "AC"),
    "BA": _p("Set/Get backlash compensation", "21", "1BA0.005", code="BA"),
    "BH": _p("Set/Get hysteresis compensation", "22", "1BH0", code="BH"),
    "DV": _p("Set/Get driver voltage", "23", "1DV48", code="DV"),
    "FD": _p("Set/Get low pass filter for Kd", "24", "1FD500", LOOP, "FD"),
    "FE": _p("Set/Get following error limit", "25", "1FE1", LOOP, "FE"),
    "FF": _p("Set/Get friction compensation", "26", "1FF0", LOOP, "FF"),
    "FR": Manual("Set/Get stepper motor configuration (not for CC)", "27", "1FR1", always="X"),
    "HT": _p("Set/Get HOME search type", "28", "1HT1", code="HT"),
    "ID": Manual("Set/Get stage identifier", "29", "1IDURS100BCC", frozenset({CF}), r"1ID\S+"),
    "JD": Manual("Leave JOGGING state", "30", "1JD", frozenset({JG})),
    "JM": Manual("Enable/disable keypad", "31", "1JM1", WORK, r"1JM[01]"),
    "JR": _p("Set/Get jerk time", "32", "1JR0.1", WORK, "JR"),
    "KD": _p("Set/Get derivative gain", "33", "1KD0", LOOP, "KD"),
    "KI": _p("Set/Get integral gain", "34", "1KI10", LOOP, "KI"),
    "KP": _p("Set/Get proportional gain", "35", "1KP100", LOOP, "KP"),
    "KV": _p("Set/Get velocity feed forward", "36", "1KV0", LOOP, "KV"),
    "MM": Manual("Enter/Leave DISABLE state", "37", "1MM0", frozenset({RD, DI}), r"1MM[0-9A-F]{2}"),
    "OH": _p("Set/Get HOME search velocity", "38", "1OH10", code="OH"),
    "OR": Manual("Execute HOME search", "39", "1OR", frozenset({NR})),
    "OT": _p("Set/Get HOME search time-out", "40", "1OT2.2", code="OT"),
    "PA": Manual("Move absolute", "41", "1PA2.2", frozenset({RD}), rf"1PA{NUM}"),
    "PR": Manual("Move relative", "42", "1PR2.2", frozenset({RD}), rf"1PR{NUM}"),
    "PT": Manual("Get motion time for a relative move", "43", "1PT2.2", frozenset({DI, RD}) | MOTION,
                 set_reply=rf"1PT{NUM}"),
    "PW": Manual("Enter/Leave CONFIGURATION state", "44", "1PW1", frozenset({NR, CF}), r"1PW[01]"),
    "QI": Manual("Set/Get motor's current limits", "45", "1QIL0.75", frozenset({CF}), rf"1QIL{NUM}",
                 query_text="1QIL?"),
    "RA": Manual("Get analog input value", "46", "1RA", ANY, set_reply=rf"1RA{NUM}"),
    "RB": Manual("Get TTL input value", "47", "1RB", ANY, set_reply=r"1RB\d+"),
    "RS": Manual("Reset controller", "48", "1RS", NOT_JOGGING),
    "SA": Manual("Set/Get controller's RS-485 address", "49", "1SA3", frozenset({CF}), r"1SA\d+"),
    "SB": Manual("Set/Get TTL output value", "50", "1SB1", frozenset({DI, RD, JG}) | MOTION, r"1SB\d+"),
    "SC": _p("Set/Get control loop state", "51", "1SC1", code="SC"),
    "SE": Manual("Configure/Execute simultaneous started move", "52", "1SE2.2", frozenset({RD})),
    "SL": _p("Set/Get negative software limit", "54", "1SL-100", WORK, "SL"),
    "SR": _p("Set/Get positive software limit", "55", "1SR100", WORK, "SR"),
    "ST": Manual("Stop motion", "56", "1ST", frozenset({DI, RD}) | MOTION),
    "SU": _p("Set/Get encoder increment value", "57", "1SU0.0001", code="SU"),
    "TB": Manual("Get command error string", "58", "1TB@", ANY, set_reply=r"1TB@ No error"),
    "TE": Manual("Get last command error", "59", "1TE", NOT_JOGGING, set_reply=r"1TE[@A-Z]"),
    "TH": Manual("Get set-point position", "60", "1TH", ANY, set_reply=rf"1TH{NUM}"),
    "TP": Manual("Get current position", "61", "1TP", ANY, set_reply=rf"1TP{NUM}"),
    "TS": Manual("Get positioner error and controller state", "62", "1TS", ANY,
                 set_reply=r"1TS[0-9A-F]{6}"),
    "VA": _p("Set/Get velocity", "64", "1VA10", WORK, "VA"),
    "VB": Manual("Set/Get base velocity (not for CC)", "65", "1VB1", always="X"),
    "VE": Manual("Get controller revision information", "66", "1VE", ANY, set_reply=r"1VE .+"),
    "ZT": Manual("Get all configuration parameters", "67", "1ZT", NOT_JOGGING,
                 set_reply=r"1PW1( / 1[A-Z]{2,3}\S*)+ / 1PW1"),
    "ZX": Manual("Set/Get ESP stage configuration", "68", "1ZX2", frozenset({CF}), r"1ZX\S+"),
}
SPECIAL_ROWS = (
    # (what, state, lines sent, manual's expectation as regex over "replies ; TE", the manual's words, page)
    ("bare ST stops all controllers", MV, ["ST"], r"; TE @$", "no address: stop every controller", "56"),
    ("0ST: address 0 is every controller", MV, ["0ST"], r"; TE @$", "ST's address range is 0 to 31", "56"),
    ("bare MM0 disables all controllers", RD, ["MM0", "1TS"], r"^1TS00003C ; TE @$",
     "MM without address or with 0: all controllers", "37"),
    ("bare SE starts the configured moves", RD, ["1SE20", "SE"], r"; TE @$", "no address: execute", "52"),
    ("PA beyond the software limit", RD, ["1PA400"], r"; TE G$", "G target position out of limits", "41"),
    ("PR beyond the software limit", RD, ["1PR-400"], r"; TE G$", "G displacement out of limits", "42"),
    ("unknown command", RD, ["1QQ"], r"; TE A$", "A unknown message code", "59"),
    ("address 0 to a query", RD, ["0TS"], r"; TE B$", "B controller address not correct (range 1 to 31)",
     "62"),
    ("parameter missing", RD, ["1PA"], r"; TE C$", "C parameter missing or out of range", "41"),
    ("OR while HOMING", HO, ["1OR"], r"; TE E$", "E home sequence already started", "39"),
    ("TE is cleared by reading it", RD, ["1QQ", "1TE"], r"1TEA ; TE @$", "TE then @", "59"),
    ("TS after power-up", NR, ["1TS"], r"^1TS00000A ; TE @$", "`1TS00000A` (the example)", "63"),
    ("TB without a code", RD, ["1QQ", "1TB"], r"^1TBA .+ ; TE @$", "explanation of the current error",
     "58"),
    ("QIR above QIL", CF, ["1QIL0.75", "1QIR1.0"], r"; TE C$", "QIR ≤ QIL, else C", "45"),
    ("SA below 2", CF, ["1SA1"], r"; TE C$", "SA range 2 to 31", "49"),
    ("ZX? answers the stage reference", RD, ["1ZX?"], r"^1ZX[A-Z]\S* ; TE @$", "`1ZXURS100CC`", "68"),
    ("PT outside its range", RD, ["1PT-5"], r"; TE C$", "range > 1e-6 and < 1e12, else C", "43"),
    ("lower case accepted", RD, ["1tp"], r"^1TP-?\d", "upper and lower case are accepted", "§5.3, 16"),
    ("blanks ignored anywhere", RD, ["1P A1 0", "1PA?"], r"^1PA10 ; TE @$",
     "`2P A1.43 6` is `2PA1.436`", "§5.3, 16"),
)


class _Port:
    """Collects what the controller writes (the conformance run needs no pty)."""

    path = "in-process"

    def __init__(self) -> None:
        self.out = bytearray()

    def write(self, data: bytes) -> None:
        self.out += data

    def read(self) -> bytes:
        return b""

    def watch_fileno(self) -> None:
        return None

    def close(self) -> None:
        pass


class _World:
    def __init__(self) -> None:
        self.table = TableMotion()


def controller_in(state: str) -> tuple[Smc100, _Port, float]:
    """A fresh controller brought into `state` the manual's way; returns it, its port, device time."""
    port = _Port()
    dev = Smc100(_World(), port=port)
    t = 0.0

    def send(text: str) -> None:
        dev.handle_line(text.encode(), t)

    if state == CF:
        send("1PW1")
    elif state == HO:
        send("1OR")
    elif state in (RD, MV, DI, JG):
        send("1OR")
        t = dev.table.move_end_s + 0.1
        dev.advance(t)
        if state == MV:
            send("1PA100")
        elif state == DI:
            send("1MM0")
        elif state == JG:
            dev.keypad_jog()  # the keypad's jog button: no command enters JOGGING (p. 30-31)
    dev.last_error = "@"
    port.out.clear()
    return dev, port, t


def run(state: str, lines: list[str]) -> str:
    """Send `lines` in `state`, then TE: 'reply / reply ; TE x'."""
    dev, port, t = controller_in(state)
    for text in lines:
        dev.handle_line(text.encode(), t)
    replies = [r for r in port.out.decode().split("\r\n") if r]
    port.out.clear()
    if state == JG and dev.state in (0x46, 0x47):
        dev.handle_line(b"1JD", t)  # TE is not accepted in JOGGING (p. 59): leave it to read TE
    dev.handle_line(b"1TE", t)
    te = port.out.decode().strip()[3:]
    return f"{' / '.join(replies)} ; TE {te}".strip()


def rows() -> list[tuple[str, str, str, str, str, str, str, bool]]:
    """(command, form, state, sent, firmware-sim answers, manual says, page, agrees)."""
    out = []
    for code, m in MANUAL.items():
        if m.query_reply is not None:
            sent = m.query_text or f"1{code}?"
            got = run(RD, [sent])
            ok = re.fullmatch(m.query_reply + r" ; TE @", got) is not None
            out.append((code, "query", RD, sent, got, f"`{m.query_reply}`, TE @", m.page, ok))
        if m.set_text is None:
            continue
        for state in STATES:
            got = run(state, [m.set_text])
            if m.always:
                want, ok = f"no reply, TE {m.always}", got == f"; TE {m.always}"
            elif state not in m.allowed:
                letter = "E" if code == "OR" and state == HO else LETTER[state]
                want, ok = f"no reply, TE {letter}", got == f"; TE {letter}"
            elif m.set_reply is not None:
                want = f"`{m.set_reply}`, TE @"
                ok = re.fullmatch(m.set_reply + r" ; TE @", got) is not None
            else:
                want, ok = "no reply, TE @", got == "; TE @"
            out.append((code, "set/execute", state, m.set_text, got, want, m.page, ok))
    for what, state, lines, pattern, words, page in SPECIAL_ROWS:
        got = run(state, lines)
        out.append((what, "rule", state, " then ".join(lines), got, words, page,
                    re.search(pattern, got) is not None))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    table = rows()
    differ = [r for r in table if not r[-1]]
    lines = [
        "# SMC100 conformance (generated by tools/conformance_smc100.py — do not edit)",
        "",
        "Every command of the Newport SMC100CC/PP user manual's command list, its query form in READY",
        "and its set/execute form in every controller state, sent to firmware-sim's controller; what",
        "it answered (reply lines, then the TE letter read after); what the manual says. Reference:",
        "\"SMC100CC & SMC100PP … User's Manual\" V3.0.x, EDH0206En2054 (06/23), §5.5 \"Command Set\";",
        "p. = its printed page (the command's page: Usage row, errors, example). The 09/18 edition",
        "EDH0206En2051 has the same Usage rows. Set and execute commands send no reply: the host reads",
        "TE. In JOGGING the TE is read after `1JD` (TE is not accepted in JOGGING, p. 59).",
        "",
        "What the manual leaves open, and firmware-sim's choice: a Usage row does not separate the set",
        "and `?` forms; queries are answered in every state (rows: READY). A command refused in",
        "JOGGING leaves D (the TE table has no JOGGING letter). PA/PR/SE refused in MOVING leave M,",
        "in HOMING L (their pages list no letter for these states; the TE table's). ZT's example",
        "shows only its first lines and its last two (`1VA80.000000`, `1ZX3`, `1PW1`): the parameters",
        "in between are firmware-sim's list.",
        "",
        f"{len(table)} rows, {len(differ)} differ from the manual.",
        "",
        "| command | form | state | sent | firmware-sim answers | the manual says | p. | agrees |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for code, form, state, sent, got, want, page, ok in table:
        title = MANUAL[code].title if code in MANUAL else ""
        name = f"{code} ({title})" if title else code
        agrees = "yes" if ok else "**no**"
        lines.append(f"| {name} | {form} | {state} | `{sent}` | `{got}` | {want} | {page} | {agrees} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"{args.out}: {len(table)} rows, {len(differ)} differ from the manual")
    for row in differ:
        print("  differs:", row)
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
