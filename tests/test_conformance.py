"""The conformance tables (tools/conformance_smc100.py, tools/conformance_canopen.py) hold: no row
differs from the manual / CiA 301, and rows are pinned with the documents' own examples."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

TOOLS = Path(__file__).resolve().parents[1] / "tools"


def _tool(name: str):
    spec = importlib.util.spec_from_file_location(name, TOOLS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def smc():
    return _tool("conformance_smc100")


@pytest.fixture(scope="module")
def co():
    return _tool("conformance_canopen")


def test_smc100_table_agrees_with_the_manual(smc):
    table = smc.rows()
    assert len(table) > 300
    assert [r for r in table if not r[-1]] == []
    commands = {r[0] for r in table}
    assert set(smc.MANUAL) <= commands  # every command of the list has its rows


@pytest.mark.parametrize("state, lines, answer", [
    # the manual's examples (EDH0206En2054, page in the comment)
    ("NOT REFERENCED", ["1TS"], "1TS00000A ; TE @"),  # p. 63
    ("READY", ["1TE"], "1TE@ ; TE @"),  # p. 59
    ("READY", ["1TB@"], "1TB@ No error ; TE @"),  # p. 58
    ("READY", ["1SR?"], "1SR360 ; TE @"),
    ("READY", ["1PA400"], "; TE G"),  # p. 41: target position out of limits
    ("MOVING", ["1PA10"], "; TE M"),  # p. 41: "only accepted in READY state"
    ("MOVING", ["1PR5"], "; TE M"),  # p. 42
    ("NOT REFERENCED", ["1AC500"], "; TE H"),  # p. 20: AC's Usage row CF DI RD
    ("READY", ["1KP100"], "; TE K"),  # p. 35: CF DI
    ("CONFIGURATION", ["1DV48"], "; TE @"),  # p. 23: DV is "Not for PP", a CC command
    ("CONFIGURATION", ["1QIL0.75", "1QIR0.25", "1QIT2.5", "1QIR?"], "1QIR0.25 ; TE @"),  # p. 45
    ("READY", ["1ZX?"], "1ZXURS100BCC ; TE @"),  # p. 68: the stage reference
    ("NOT REFERENCED", ["1ST"], "; TE H"),  # p. 56: ST in DI RD and motion
    ("MOVING", ["1OR"], "; TE M"),
    ("CONFIGURATION", ["1PA10"], "; TE I"),
    ("READY", ["1VB1"], "; TE X"),  # "Not for CC"
    ("READY", ["1TBH"], "1TBH Command not allowed in NOT REFERENCED state ; TE @"),
])
def test_smc100_rows_pinned_with_manual_examples(smc, state, lines, answer):
    assert smc.run(state, lines) == answer


def test_smc100_zt_dump_as_the_manuals_example(smc):
    """p. 67: `1PW1`, `1AC320.000000`, `1BA0.000000`, …, `1VA80.000000`, `1ZX3`, `1PW1`."""
    got = smc.run("READY", ["1ZT"]).split(" ; ")[0].split(" / ")
    assert got[0] == "1PW1" and got[-1] == "1PW1"
    from firmware_sim.devices.smc100 import ZT_ORDER

    assert [line[1:].rstrip("0123456789.-") for line in got[1:-1]] == list(ZT_ORDER)
    assert got[1] == "1AC80.000000" and got[2] == "1BA0.000000" and got[-2] == "1ZX2"


def test_smc100_ts_clears_the_positioner_errors_it_reports(smc):
    """p. 63: TS reads the error buffer and clears it (as TE and TB do)."""
    dev, port, t = smc.controller_in("READY")
    dev.errors = 0x20
    dev.handle_line(b"1TS", t)
    dev.handle_line(b"1TS", t)
    assert port.out.decode().split() == ["1TS002032", "1TS000032"]


def test_smc100_jogging_is_the_keypads_and_te_is_not_accepted_there(smc):
    dev, port, t = smc.controller_in("READY")
    dev.handle_line(b"1JM0", t)  # p. 31: keypad disabled
    dev.keypad_jog()
    assert dev.state == 0x32
    dev.handle_line(b"1JM1", t)
    dev.keypad_jog()
    assert dev.state == 0x46  # JOGGING from READY
    dev.handle_line(b"1TE", t)
    assert port.out == b""  # p. 59: TE not accepted in JOGGING
    dev.handle_line(b"1JD", t)
    dev.handle_line(b"1TE", t)
    assert dev.state == 0x35 and port.out == b"1TED\r\n"


def test_smc100_bare_st_stops_the_move(smc):
    dev, port, t = smc.controller_in("MOVING")
    dev.handle_line(b"ST", t)
    assert dev.target_deg < 100.0  # the move to 100 (controller_in) is cut short, in device time
    dev.advance(dev.table.move_end_s + 0.01)
    assert dev.state == 0x33 and dev.last_error == "@"
    dev.handle_line(b"MM0", t)  # p. 37: MM without an address, every controller
    assert dev.state == 0x3C and dev.last_error == "@"


def test_canopen_table_agrees_with_cia301(co):
    table = co.object_rows() + co.rule_rows() + co.behaviour_rows()
    assert len(table) > 100
    assert [r for r in table if not r[-1]] == []


def test_canopen_procedure_rows_pinned(co):
    """CiA 301 §7.5.2.38's own sequence on one node: invalidate, count 0, entries, count, validate."""
    b = co.Bench()
    try:
        assert b.write(0x1800, 1, "u32", 0x80000190) == "ok"
        assert b.write(0x1A00, 0, "u8", 0) == "ok"
        assert b.write(0x1A00, 1, "u32", 0x20000320) == "ok"
        assert b.write(0x1A00, 2, "u32", 0x20020008) == "ok"
        assert b.write(0x1A00, 0, "u8", 2) == "ok"
        assert b.write(0x1800, 1, "u32", 0x190) == "ok"
        assert b.read(0x1A00, 0) == "0x02" and b.read(0x1800, 1) == "0x00000190"
        b.nmt(0x01)
        frames = [m for m in b.step(0.1) if m.arbitration_id == 0x190]
        assert len(frames) == 10 and all(len(m.data) == 5 for m in frames)
    finally:
        b.close()
