"""Every function of the package fits on a screen or so (80 lines), and every class
in the head (300): the limits the project holds itself to (docs/architecture.md)."""

from __future__ import annotations

import ast
from pathlib import Path

import imu_gateway

ROOT = Path(imu_gateway.__file__).parent
FUNCTION_LINES, CLASS_LINES = 80, 300


def sizes() -> list[tuple[str, str, int]]:
    found = []
    for path in sorted(ROOT.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                lines = (node.end_lineno or node.lineno) - node.lineno + 1
                kind = "class" if isinstance(node, ast.ClassDef) else "function"
                found.append((kind, f"{path.relative_to(ROOT)}:{node.lineno} {node.name}",
                              lines))
    return found


def test_no_function_over_80_lines_and_no_class_over_300() -> None:
    found = sizes()
    assert len(found) > 500  # the walk saw the package
    too_long = [f"{kind} {where}: {lines} lines" for kind, where, lines in found
                if lines > (CLASS_LINES if kind == "class" else FUNCTION_LINES)]
    assert too_long == []
