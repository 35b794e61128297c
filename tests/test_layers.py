"""The package's import graph against the layers of docs/architecture.md: every module in a layer, no import
from a lower layer (or an earlier stage) to a higher one (a later stage), and no cycle."""

from __future__ import annotations

import ast
import fnmatch
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "ffrecon"


def _modules() -> dict[str, Path]:
    found = {}
    for path in PACKAGE.rglob("*.py"):
        name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        found[name.removesuffix(".__init__")] = path
    return found


def _imports(path: Path, modules: dict[str, Path]) -> set[str]:
    """The package's modules ``path`` imports: at the top, inside functions and under TYPE_CHECKING alike."""
    deps = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("ffrecon"):
            deps.add(node.module)
            deps |= {f"{node.module}.{a.name}" for a in node.names if f"{node.module}.{a.name}" in modules}
        elif isinstance(node, ast.Import):
            deps |= {a.name for a in node.names if a.name.startswith("ffrecon")}
    return {d for d in deps if d in modules}


def _layers() -> list[list[str]]:
    """The ordered rungs of docs/architecture.md's ``layers`` block: one list of patterns per rung (a layer,
    or one stage of the stage layer)."""
    text = (ROOT / "docs" / "architecture.md").read_text()
    block = re.search(r"```layers\n(.*?)```", text, re.S)
    assert block, "docs/architecture.md has no ```layers block"
    rungs = []
    for line in block.group(1).strip().splitlines():
        _, patterns = line.split(":", 1)
        rungs += [part.split() for part in patterns.split("|")]
    return rungs


def _rung(module: str, rungs: list[list[str]]) -> tuple[int, str]:
    """``(rung index, layer name)`` of a module; a package's own ``__init__`` matches ``pkg.*`` too."""
    for k, patterns in enumerate(rungs):
        if any(module == p or fnmatch.fnmatchcase(module, p) or f"{module}.*" == p for p in patterns):
            return k, " ".join(patterns)
    raise AssertionError(f"{module} is in no layer of docs/architecture.md")


def _graph() -> dict[str, set[str]]:
    """Module -> the modules it imports, without its own packages (importing ``ffrecon.sfm.x`` runs the
    ``__init__`` of ``ffrecon.sfm`` first, which may import ``x``: Python's order, not a cycle)."""
    modules = _modules()
    return {
        name: {d for d in _imports(path, modules) if d != name and not name.startswith(d + ".")}
        for name, path in modules.items()
    }


def test_every_module_is_in_a_layer():
    rungs = _layers()
    missing = []
    for module in _modules():
        try:
            _rung(module, rungs)
        except AssertionError as err:
            missing.append(str(err))
    assert not missing, missing


def test_no_import_runs_up_a_layer_or_to_a_later_stage():
    rungs = _layers()
    upward = []
    for module, deps in _graph().items():
        here, _ = _rung(module, rungs)
        for dep in deps:
            there, layer = _rung(dep, rungs)
            if there > here:
                upward.append(f"{module} imports {dep} ({layer})")
    assert not upward, "\n".join(sorted(upward))


def test_the_import_graph_has_no_cycle():
    graph = _graph()
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(module: str, path: list[str]) -> list[str] | None:
        state[module] = 1
        for dep in sorted(graph[module]):
            if state.get(dep) == 1:
                return path[path.index(dep) :] + [dep] if dep in path else [module, dep]
            if dep not in state and (cycle := visit(dep, [*path, dep])):
                return cycle
        state[module] = 2
        return None

    for module in sorted(graph):
        if module not in state and (cycle := visit(module, [module])):
            pytest.fail("import cycle: " + " -> ".join(cycle))


def test_the_check_sees_a_violation(tmp_path):
    """The layer rule is not vacuous: a kernel importing the pipeline is found."""
    rungs = _layers()
    kernel, _ = _rung("ffrecon.types", rungs)
    pipeline, _ = _rung("ffrecon.pipeline", rungs)
    capture, _ = _rung("ffrecon.capture.images", rungs)
    splat, _ = _rung("ffrecon.splat.stage", rungs)
    assert kernel < capture < splat < pipeline
    probe = tmp_path / "probe.py"
    probe.write_text("def f():\n    from ffrecon.pipeline import run\n")
    assert _imports(probe, _modules()) == {"ffrecon.pipeline"}
