"""The SMC100 conformance table: every command of the user manual's command list, in its query
form and its set/execute form in each controller state, sent to firmware-sim's controller → what
it answers (reply lines and the TE letter read after) → what the manual says.

The manual's expectations are written here from the manual's command list (allowed states per
command), the command descriptions (reply formats) and the TE table, independently of the
simulator's own tables. Writes docs/conformance/smc100.md and prints the row count and every row
that differs; exit status 1 when any does.

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
ANY = frozenset(STATES)
WORK = frozenset({NR, CF, DI, RD})

NUM = r"-?\d+(\.\d+)?"


@dataclass(frozen=True)
class Manual:
    """One command as the manual gives it: a set/execute example, the states it is allowed in,
    the query form's reply (regex), or a letter the manual gives for every state (W/X)."""

    title: str
    set_text: str | None
    allowed: frozenset[str] = frozenset({CF})
    query_reply: str | None = None
    always: str | None = None  # e.g. X: not for the CC version
    set_reply: str | None = None  # a command whose execute form answers (PT, TB, …)


def _p(title: str, example: str, allowed: frozenset[str] = frozenset({CF}), code: str = "") -> Manual:
    return Manual(title, example, allowed, rf"1{code}{NUM}")


MANUAL: dict[str, Manual] = {
    "AC": _p("Set/Get acceleration", "1AC50", WORK, "AC"),
    "BA": _p("Set/Get backlash compensation", "1BA0", code="BA"),
    "BH": _p("Set/Get hysteresis compensation", "1BH0", code="BH"),
    "DV": Manual("Set/Get driver voltage (PP)", "1DV12", always="X"),
    "FD": _p("Set/Get low pass filter for Kd", "1FD500", WORK, "FD"),
    "FE": _p("Set/Get following error limit", "1FE1", WORK, "FE"),
    "FF": _p("Set/Get friction compensation", "1FF0", WORK, "FF"),
    "FR": Manual("Set/Get stepper motor configuration (PP)", "1FR1", always="X"),
    "HT": _p("Set/Get HOME search type", "1HT1", code="HT"),
    "ID": Manual("Set/Get stage identifier", "1IDURS100BCC", frozenset({CF}), r"1ID\S+"),
    "JD": Manual("Leave JOGGING state", "1JD", frozenset({JG})),
    "JM": Manual("Enter/Leave JOGGING state", "1JM1", frozenset({RD, DI, JG}), r"1JM[01]"),
    "JR": _p("Set/Get jerk time", "1JR0.1", WORK, "JR"),
    "KD": _p("Set/Get derivative gain", "1KD0", WORK, "KD"),
    "KI": _p("Set/Get integral gain", "1KI10", WORK, "KI"),
    "KP": _p("Set/Get proportional gain", "1KP100", WORK, "KP"),
    "KV": _p("Set/Get velocity feed forward", "1KV0", WORK, "KV"),
    "MM": Manual("Enter/Leave DISABLE state", "1MM0", frozenset({RD, DI}), r"1MM[0-9A-F]{2}"),
    "OH": _p("Set/Get HOME search velocity", "1OH10", code="OH"),
    "OR": Manual("Execute HOME search", "1OR", frozenset({NR})),
    "OT": _p("Set/Get HOME search time-out", "1OT50", code="OT"),
    "PA": Manual("Move absolute", "1PA10", frozenset({RD, MV}), rf"1PA{NUM}"),
    "PR": Manual("Move relative", "1PR5", frozenset({RD, MV})),
    "PT": Manual("Get motion time for a relative move", "1PT10", ANY, set_reply=rf"1PT{NUM}"),
    "PW": Manual("Enter/Leave CONFIGURATION state", "1PW1", frozenset({NR, CF}), r"1PW[01]"),
    "QI": _p("Set/Get motor's current limits", "1QI1", code="QI"),
    "RA": Manual("Get analog input value", "1RA", ANY, set_reply=rf"1RA{NUM}"),
    "RB": Manual("Get TTL input value", "1RB", ANY, set_reply=r"1RB\d+"),
    "RS": Manual("Reset controller", "1RS", ANY),
    "SA": Manual("Set/Get controller's RS-485 address", "1SA2", frozenset({CF}), r"1SA\d+"),
    "SB": Manual("Set/Get TTL output value", "1SB1", ANY, r"1SB\d+"),
    "SC": _p("Set/Get control loop state", "1SC1", WORK, "SC"),
    "SE": Manual("Configure/Execute simultaneous started move", "1SE10", frozenset({RD})),
    "SL": _p("Set/Get negative software limit", "1SL-100", WORK, "SL"),
    "SR": _p("Set/Get positive software limit", "1SR100", WORK, "SR"),
    "ST": Manual("Stop motion", "1ST", ANY),
    "SU": _p("Set/Get encoder increment value", "1SU0.0001", code="SU"),
    "TB": Manual("Get command error string", "1TBC", ANY, set_reply=r"1TBC .+"),
    "TE": Manual("Get command error", "1TE", ANY, set_reply=r"1TE[@A-Z]"),
    "TH": Manual("Get set-point position", "1TH", ANY, set_reply=rf"1TH{NUM}"),
    "TP": Manual("Get current position", "1TP", ANY, set_reply=rf"1TP{NUM}"),
    "TS": Manual("Get positioner error and controller state", "1TS", ANY, set_reply=r"1TS[0-9A-F]{6}"),
    "VA": _p("Set/Get velocity", "1VA10", WORK, "VA"),
    "VB": Manual("Set/Get base velocity (PP)", "1VB1", always="X"),
    "VE": Manual("Get controller revision information", "1VE", ANY, set_reply=r"1VE .+"),
    "ZT": Manual("Get all axis parameters", "1ZT", ANY, set_reply=r"1PW1( / 1[A-Z]{2}\S*)+ / 1PW0"),
    "ZX": _p("Set/Get SmartStage configuration", "1ZX2", frozenset({NR, CF}), "ZX"),
}
SPECIAL_ROWS = (
    # (what, state, lines sent, manual's expectation as regex over "replies ; TE", the manual's words)
    ("bare ST stops all controllers", MV, ["ST"], r"; TE @$", "no address: stop every controller"),
    ("bare SE starts the configured moves", RD, ["1SE20", "SE"], r"; TE @$", "no address: execute"),
    ("PA beyond the software limit", RD, ["1PA400"], r"; TE G$", "G displacement out of limits"),
    ("PR beyond the software limit", RD, ["1PR-400"], r"; TE G$", "G displacement out of limits"),
    ("unknown command", RD, ["1QQ"], r"; TE A$", "A unknown message code"),
    ("address 0", RD, ["0TS"], r"; TE B$", "B controller address not correct"),
    ("parameter missing", RD, ["1PA"], r"; TE C$", "C parameter missing or out of range"),
    ("OR while HOMING", HO, ["1OR"], r"; TE E$", "E home sequence already started"),
    ("TE is cleared by reading it", RD, ["1QQ", "1TE"], r"1TEA ; TE @$", "TE then @"),
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
            send("1JM1")
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
    dev.handle_line(b"1TE", t)
    te = port.out.decode().strip()[3:]
    return f"{' / '.join(replies)} ; TE {te}".strip()


def rows() -> list[tuple[str, str, str, str, str, str, bool]]:
    """(command, form, state, sent, firmware-sim answers, manual says, agrees)."""
    out = []
    for code, m in MANUAL.items():
        if m.query_reply is not None:
            got = run(RD, [f"1{code}?"])
            ok = re.fullmatch(m.query_reply + r" ; TE @", got) is not None
            out.append((code, "query", RD, f"1{code}?", got, f"`{m.query_reply}`, TE @", ok))
        if m.set_text is None:
            continue
        for state in STATES:
            got = run(state, [m.set_text])
            if m.always:
                want, ok = f"no reply, TE {m.always}", got == f"; TE {m.always}"
            elif m.set_reply is not None:
                want = f"`{m.set_reply}`, TE @"
                ok = re.fullmatch(m.set_reply + r" ; TE @", got) is not None
            elif state in m.allowed:
                want, ok = "no reply, TE @", got == "; TE @"
            else:
                letter = "E" if code == "OR" and state == HO else LETTER[state]
                want, ok = f"no reply, TE {letter}", got == f"; TE {letter}"
            out.append((code, "set/execute", state, m.set_text, got, want, ok))
    for what, state, lines, pattern, words in SPECIAL_ROWS:
        got = run(state, lines)
        out.append((what, "rule", state, " then ".join(lines), got, words,
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
        "Every command of the Newport SMC100CC/PP user manual's command list (Remote Mode), its query",
        "form in READY and its set/execute form in every controller state, sent to firmware-sim's",
        "controller; what it answered (reply lines, then the TE letter read after); what the manual",
        "says (allowed states, reply format, TE table). Set and execute commands send no reply in the",
        "manual: the host reads TE.",
        "",
        f"{len(table)} rows, {len(differ)} differ from the manual.",
        "",
        "| command | form | state | sent | firmware-sim answers | the manual says | agrees |",
        "|---|---|---|---|---|---|---|",
    ]
    for code, form, state, sent, got, want, ok in table:
        title = MANUAL[code].title if code in MANUAL else ""
        name = f"{code} ({title})" if title else code
        agrees = "yes" if ok else "**no**"
        lines.append(f"| {name} | {form} | {state} | `{sent}` | `{got}` | {want} | {agrees} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"{args.out}: {len(table)} rows, {len(differ)} differ from the manual")
    for row in differ:
        print("  differs:", row)
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
