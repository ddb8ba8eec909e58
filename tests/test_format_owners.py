"""One owner per format: a path inside a corpus or a shard member's name is spelled in ``marionette/corpus/`` alone,
and a recording's file names in ``marionette/recordings/`` alone; every other module imports the names (a docstring
or a message may still say them)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OWNERS = (ROOT / "marionette" / "corpus", ROOT / "marionette" / "recordings")
# file names a corpus or a recording holds (members of a shard, metadata files, a recording's files)
NAMES = {
    "rgb.mp4",
    "pose.gbz",
    "pose.json",
    "depth.mkv",
    "state.csv",
    "skeleton.npz",
    "info.json",
    "segments.parquet",
    "samples.parquet",
    "quarantine.parquet",
    "vocab.json",
    "stats.json",
    "scan.json",
    "stages.json",
}
# a corpus's directories: a literal joined onto a path (``path / "meta"``, ``Path("meta")``) is a corpus path
DIRS = {"meta", "derived", "staging", "state", "video", "terrain", "pose", "samples", "builds"}


def spelled(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, text) of every corpus or recording name a module spells outside docstrings and f-strings."""
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                skip.add(id(first.value))
        if isinstance(node, ast.JoinedStr):
            skip.update(id(v) for v in node.values)
    joined: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div):
            joined.update((id(node.left), id(node.right)))
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "Path":
            joined.update(id(a) for a in node.args)
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Constant) or not isinstance(node.value, str) or id(node) in skip:
            continue
        text = node.value
        if text in NAMES or text.startswith(("meta/", "derived/")) or (text in DIRS and id(node) in joined):
            found.append((node.lineno, text))
    return found


def test_corpus_paths_and_member_names_are_spelled_by_their_owners_alone():
    files = [p for d in ("marionette", "terrain_scan", "flows") for p in sorted((ROOT / d).rglob("*.py"))]
    assert len(files) > 80
    bad = [
        f"{p.relative_to(ROOT)}:{line}: {text!r}"
        for p in files
        if not any(owner in p.parents for owner in OWNERS)
        for line, text in spelled(ast.parse(p.read_text()))
    ]
    assert bad == []


def test_the_check_finds_a_spelled_name():
    source = 'import json\nfrom pathlib import Path\n\n\ndef f(c):\n    """Reads meta/info.json."""\n'
    source += '    return Path(c) / "meta" / "info.json", f"{c}/meta", {"kind": "pose"}["kind"]\n'
    assert sorted(spelled(ast.parse(source))) == [(7, "info.json"), (7, "meta")]


def rate_literals(tree: ast.AST) -> list[int]:
    """Lines where a frame rate defaults to the model rate spelled as a number: a parameter, field or
    ``.get("fps", ...)`` named for a rate (``fps``, ``*_fps``) given 20, beside ``corpus.MODEL_FPS``."""

    def rate(name: str | None) -> bool:
        return bool(name) and (name == "fps" or name.endswith("_fps"))

    def number(node: ast.AST | None) -> bool:
        return isinstance(node, ast.Constant) and type(node.value) in (int, float) and node.value == 20

    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            args = node.args
            positional = args.posonlyargs + args.args
            pairs = list(zip(positional[len(positional) - len(args.defaults) :], args.defaults))
            pairs += [(a, d) for a, d in zip(args.kwonlyargs, args.kw_defaults) if d is not None]
            found += [d.lineno for a, d in pairs if rate(a.arg) and number(d)]
        elif isinstance(node, ast.AnnAssign | ast.Assign):
            targets = [node.target] if isinstance(node, ast.AnnAssign) else node.targets
            if any(rate(getattr(t, "id", None)) for t in targets) and number(node.value):
                found.append(node.lineno)
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "get" and len(node.args) == 2:
            key, default = node.args
            if isinstance(key, ast.Constant) and isinstance(key.value, str) and rate(key.value) and number(default):
                found.append(node.lineno)
    return found


def test_the_model_rate_is_one_named_constant():
    files = [p for d in ("marionette", "terrain_scan", "flows") for p in sorted((ROOT / d).rglob("*.py"))]
    owner = ROOT / "marionette" / "corpus" / "__init__.py"
    bad = [f"{p.relative_to(ROOT)}:{line}" for p in files if p != owner for line in rate_literals(ast.parse(p.read_text()))]
    assert bad == []


def test_the_rate_check_finds_a_spelled_rate():
    source = "def f(c, fps: float = 20.0, *, model_fps=20):\n    return c.get('fps', 20.0)\n\n\nclass A:\n    fps = 20.0\n"
    source += "\n\ndef g(fps=MODEL_FPS, size=20.0, source_fps=30.0):\n    return {}.get('fps', MODEL_FPS)\n"
    assert sorted(rate_literals(ast.parse(source))) == [1, 1, 2, 6]
