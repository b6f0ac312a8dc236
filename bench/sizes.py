"""The functions over 80 lines and the classes over 250 in fbspost/ (docs/architecture.md, "exceptions").

Run from the repository root:  python bench/sizes.py
Counts the lines from ``def`` / ``class`` to the last line of the body (nested ones too).
Exit status 1 when any is over.
"""
from __future__ import annotations

import ast
import sys
from pathlib import Path

LIMITS = {ast.ClassDef: 250, ast.FunctionDef: 80, ast.AsyncFunctionDef: 80}


def offenders(folder: Path) -> list[tuple[str, int]]:
    found = []
    for path in sorted(folder.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            limit = LIMITS.get(type(node))
            if limit is not None and node.end_lineno - node.lineno + 1 > limit:
                found.append((f"{path.stem}.{node.name}", node.end_lineno - node.lineno + 1))
    return found


if __name__ == "__main__":
    over = offenders(Path(__file__).resolve().parents[1] / "fbspost")
    for name, lines in over:
        print(f"{name} {lines}")
    sys.exit(1 if over else 0)
