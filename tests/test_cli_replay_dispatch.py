"""`northfinder replay` recognises an align run by its kind and replays it with the mode's code."""

from __future__ import annotations

import json

import pytest

from northfinder.cli import main


@pytest.mark.slow
def test_replay_dispatches_an_align_gnss_run(tmp_path, capsys):
    run_dir = tmp_path / "gnss"
    rc = main(["align", "--mode", "gnss", "--simulate", "--duration", "30", "--heading-error", "45",
               "--seed", "3", "--time-scale", "20", "--out", str(run_dir)])
    assert rc == 0
    assert json.loads((run_dir / "config.json").read_text())["kind"] == "align-gnss"
    capsys.readouterr()
    assert main(["replay", str(run_dir), "--quiet"]) == 0
    line = capsys.readouterr().out.strip().splitlines()[0]
    assert "complete align-gnss run" in line and "identical to the live result.json" in line, line


def test_every_kind_registers_its_measure_compute_replay_and_history_row():
    """northfinder.runkinds: each kind of run once, its four functions found by import path."""
    from northfinder import runkinds

    assert sorted(runkinds.KINDS) == ["align-gnss", "align-swaying", "campaign", "find"]
    for kind in runkinds.KINDS.values():
        for target in (kind.measure_at, kind.compute_at, kind.replay_at, kind.history_row_at):
            assert callable(runkinds._resolve(target)), (kind.kind, target)


def test_the_kind_of_a_run_directory(tmp_path):
    """config.json's kind; a campaign directory by its campaign.json; a find when nothing says."""
    from northfinder import runkinds

    for kind in ("align-gnss", "align-swaying", "find"):
        d = tmp_path / kind
        d.mkdir()
        (d / "config.json").write_text(json.dumps({"kind": kind}))
        assert runkinds.kind_of(d).kind == kind
    (tmp_path / "camp").mkdir()
    (tmp_path / "camp" / "campaign.json").write_text("{}")
    assert runkinds.kind_of(tmp_path / "camp").kind == "campaign"
    assert runkinds.kind_of(tmp_path / "nothing-here").kind == "find"
