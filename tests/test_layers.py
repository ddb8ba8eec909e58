"""The import layers (``[tool.importlinter]`` in pyproject.toml, checked by ``lint-imports`` in the README's test
command): every package and module has a layer, no module imports another in a cycle, and the linter fails a package
whose lower layer imports a higher one."""

from __future__ import annotations

import os
import pkgutil
import subprocess
import sys
import tomllib
from pathlib import Path

import grimp

ROOT = Path(__file__).resolve().parent.parent
ROOTS = ("marionette", "terrain_scan", "flows")


def contract_layers() -> list[list[str]]:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    (contract,) = config["contracts"]
    assert contract["type"] == "layers" and tuple(config["root_packages"]) == ROOTS
    return [[name.strip() for name in layer.split("|")] for layer in contract["layers"]]


def test_every_package_and_module_has_one_layer():
    named = [name for layer in contract_layers() for name in layer]
    assert len(named) == len(set(named))
    children = {f"marionette.{m.name}" for m in pkgutil.iter_modules([str(ROOT / "marionette")])}
    assert children | {"terrain_scan", "flows"} == set(named)


def test_no_module_imports_itself_through_others():
    graph = grimp.build_graph(*ROOTS)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.find_modules_directly_imported_by(v):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            part = []
            while True:
                w = stack.pop()
                on.discard(w)
                part.append(w)
                if w == v:
                    break
            if len(part) > 1:
                cycles.append(sorted(part))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10 * len(graph.modules)))
    for module in sorted(graph.modules):
        if module not in index:
            visit(module)
    assert cycles == []


def test_lint_imports_fails_an_upward_import(tmp_path):
    package = tmp_path / "layered"
    for name, text in {
        "__init__.py": "",
        "high.py": "from layered import low\n",
        "low.py": "def f():\n    from layered import high  # a lower layer reaching up, inside a function\n",
    }.items():
        (package / name).parent.mkdir(exist_ok=True)
        (package / name).write_text(text)
    (tmp_path / ".importlinter").write_text(
        "[importlinter]\nroot_package = layered\n\n[importlinter:contract:layers]\nname = down\ntype = layers\n"
        "layers =\n    layered.high\n    layered.low\n"
    )
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    lint = str(Path(sys.executable).with_name("lint-imports"))
    done = subprocess.run([lint, "--no-cache"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 1 and "layered.low -> layered.high" in done.stdout
