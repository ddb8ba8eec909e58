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
    "pose.mkv",
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
