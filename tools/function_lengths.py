"""Print every function (and method) of northfinder/ longer than a limit, longest first, and the
line count of sequencer.py: the house's "a function over ~60 lines hides a concept" check.

A function's length is from its `def` (decorators excluded) to its last line, docstring included.
Usage: python tools/function_lengths.py [LIMIT] (default 60).
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def long_functions(package: Path, limit: int) -> list[tuple[int, str, str]]:
    """(lines, file, qualified name) of every function of `package` longer than `limit` lines."""
    out = []
    for path in sorted(package.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        stack: list[tuple[ast.AST, str]] = [(tree, "")]
        while stack:
            node, prefix = stack.pop()
            for child in ast.iter_child_nodes(node):
                if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                    name = f"{prefix}{child.name}"
                    if not isinstance(child, ast.ClassDef):
                        n = child.end_lineno - child.lineno + 1
                        if n > limit:
                            out.append((n, str(path.relative_to(ROOT)), name))
                    stack.append((child, name + "."))
    return sorted(out, key=lambda r: (-r[0], r[1], r[2]))


def main() -> None:
    limit = int(sys.argv[1]) if len(sys.argv) > 1 else 60
    seq = ROOT / "northfinder" / "sequencer.py"
    print(f"northfinder/sequencer.py: {len(seq.read_text(encoding='utf-8').splitlines())} lines")
    found = long_functions(ROOT / "northfinder", limit)
    print(f"functions over {limit} lines in northfinder/: {len(found)}")
    for n, path, name in found:
        print(f"{n:5d}  {path}  {name}")


if __name__ == "__main__":
    main()
