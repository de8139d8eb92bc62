"""The README's library example runs as written, and its commands are the ones CI runs."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text()


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", README, flags=re.S)


def test_library_example_runs(capsys):
    (example,) = [b for b in _blocks("python") if "solve_heading" in b]
    exec(compile(example, "README.md", "exec"), {})
    out = capsys.readouterr().out
    match = re.search(r"heading ([\d.]+) ± ([\d.]+)°", out)
    assert match, out
    heading, sigma = float(match.group(1)), float(match.group(2))
    assert abs(heading - 123.0) < 4 * sigma  # the example's truth, within its own 1σ band × 4


def test_ci_runs_the_readme_commands():
    ci = (ROOT / ".ci" / "run").read_text()
    bash = "\n".join(_blocks("bash"))
    install = next(line for line in bash.splitlines() if "pip install" in line)
    test = next(line for line in bash.splitlines() if "pytest" in line)
    assert install in ci and test in ci
    assert "northfinder find --simulate" in bash
