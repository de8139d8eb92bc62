"""The layers are a contract checked by a tool: import-linter's `lint-imports` with the contracts in
pyproject.toml (northfinder's layers, northfinder ⇄ firmware_sim independence, firmware_sim's own
SDO server, pure estimators/align/codecs). A second test breaks a layer on a copy of the tree and
shows the tool catches it, so the first test cannot pass by checking nothing.

The tool runs in this interpreter (``sys.executable``, import-linter's own command function), so
the venv's import-linter is used whether or not its bin is on PATH; skipped only when import-linter
is not installed at all."""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# `lint-imports` is import-linter's console script for this function; the package has no __main__
LINT_IMPORTS = [sys.executable, "-c", "import sys; from importlinter.cli import lint_imports_command; "
                "sys.exit(lint_imports_command())"]
needs_tool = pytest.mark.skipif(
    importlib.util.find_spec("importlinter") is None,
    reason="import-linter is not installed (pip install -e '.[test]')",
)


def _lint(cwd: Path) -> subprocess.CompletedProcess[str]:
    # the copy's packages must win over the editable install: put the copy first on sys.path
    env = {"PYTHONPATH": str(cwd), "PATH": str(Path(sys.executable).parent) + ":/usr/bin:/bin"}
    return subprocess.run(
        [*LINT_IMPORTS, "--no-cache"], cwd=cwd, capture_output=True, text=True, env=env, timeout=120
    )


@needs_tool
def test_every_contract_is_kept():
    proc = _lint(ROOT)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "broken" not in proc.stdout.lower() or " 0 broken" in proc.stdout


@needs_tool
@pytest.mark.parametrize(
    ("module", "line", "contract"),
    [
        ("northfinder/align/__init__.py", "import northfinder.cli", "northfinder layers"),
        ("northfinder/estimators/__init__.py", "import matplotlib", "pure mathematics"),
        ("firmware_sim/__init__.py", "import northfinder.constants", "independent implementations"),
    ],
)
def test_a_broken_contract_fails(tmp_path, module, line, contract):
    for name in ("northfinder", "firmware_sim"):
        shutil.copytree(ROOT / name, tmp_path / name, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    target = tmp_path / module
    target.write_text(target.read_text() + f"\n{line}  # deliberately breaks a contract\n")
    proc = _lint(tmp_path)
    assert proc.returncode != 0, proc.stdout
    assert contract in proc.stdout and "BROKEN" in proc.stdout, proc.stdout
