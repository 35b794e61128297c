"""The code's shape: short functions (or a stated reason), no docstring pointing outside the repository."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "ffrecon"
MAX_LINES = 60


def _functions():
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                yield path, node


def _code_lines(node) -> int:
    """Lines of a function without its docstring (documentation is not length)."""
    lines = node.end_lineno - node.lineno + 1
    first = node.body[0]
    if isinstance(first, ast.Expr) and isinstance(getattr(first, "value", None), ast.Constant):
        lines -= first.end_lineno - first.lineno + 1
    return lines


def test_no_function_over_60_lines_without_a_reason():
    long = [
        f"{path.relative_to(PACKAGE.parent)}::{node.name} ({_code_lines(node)} lines)"
        for path, node in _functions()
        if _code_lines(node) > MAX_LINES and "Long because" not in (ast.get_docstring(node) or "")
    ]
    assert not long, "split these, or say why in the docstring ('Long because ...'): " + ", ".join(long)


def test_no_docstring_points_outside_the_repository():
    outside = [
        f"{path.relative_to(PACKAGE.parent)}::{getattr(node, 'name', 'module')}"
        for path in sorted(PACKAGE.rglob("*.py"))
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.ClassDef, ast.AsyncFunctionDef))
        and any(word in (ast.get_docstring(node) or "") for word in ("CONTRACTS.md", "../shared", "STYLE.md"))
    ]
    assert not outside, "summarise the contract in docs/ and point there: " + ", ".join(outside)
