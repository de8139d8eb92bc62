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
