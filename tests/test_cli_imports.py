"""The command line reads its options and summarises a corpus without loading a heavy library: every ``--help`` and
``marionette inspect`` run in a fresh interpreter and name the heavy modules they imported."""

from __future__ import annotations

import json
import subprocess
import sys

HEAVY = ("torch", "open3d", "prefect", "diffusers", "moderngl")

# Runs each argv through ``marionette.cli.main`` in one fresh interpreter (SystemExit from --help caught, output
# dropped) and prints the heavy modules then loaded, with the commands it ran.
PROBE = """
import argparse, contextlib, io, json, sys
from marionette.cli import build_parser, main

argvs = json.loads(sys.argv[1])
if argvs == "every --help":
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    argvs = [["--help"]]
    for name, parser in sub.choices.items():
        inner = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        argvs += [[name, n, "--help"] for n in inner[0].choices] if inner else [[name, "--help"]]
for argv in argvs:
    with contextlib.redirect_stdout(io.StringIO()) as out:
        try:
            code = main(argv)
        except SystemExit as exc:
            code = exc.code
    assert code in (0, None), (argv, code)
    assert out.getvalue(), argv
heavy = json.loads(sys.argv[2])
print(json.dumps({"ran": argvs, "loaded": [m for m in heavy if m in sys.modules]}))
"""


def probe(argvs, heavy=HEAVY) -> dict:
    done = subprocess.run(
        [sys.executable, "-c", PROBE, json.dumps(argvs), json.dumps(heavy)], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_every_help_imports_no_heavy_library():
    got = probe("every --help")
    commands = {" ".join(a[:-1]) for a in got["ran"]}
    assert {"", "ingest", "train dynamics", "train observation", "train wan", "generate", "rollout", "play", "eval"} <= commands
    assert len(commands) >= 19
    assert got["loaded"] == []


def test_inspect_imports_no_heavy_library(corpus):
    got = probe([["inspect", str(corpus)], ["inspect", str(corpus), "--segments"], ["inspect", str(corpus), "--json"]])
    assert got["loaded"] == []


def test_the_probe_names_what_was_loaded():
    """The check can fail: asked about modules ``--help`` does load, the probe names them."""
    assert probe([["--help"]], heavy=("marionette.knobs", "torch"))["loaded"] == ["marionette.knobs"]
