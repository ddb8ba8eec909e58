"""scripts/compare_demo_runs.py: two runs' files and report values compared, the differences two runs of the same
code show explained, anything else named and failed."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
from safetensors.numpy import save_file

SCRIPT = Path(__file__).resolve().parent.parent / "scripts" / "compare_demo_runs.py"


def load():
    spec = importlib.util.spec_from_file_location("compare_demo_runs", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run_dir(root: Path, mtime: int, rng: int, loss: float) -> Path:
    (root / "corpus" / "meta" / "samples").mkdir(parents=True)
    (root / "evaluation").mkdir()
    (root / "dynamics" / "step-1").mkdir(parents=True)
    record = {"files": {"rgb.mp4": [10, mtime, "ab" * 32]}, "frames": 30}
    (root / "corpus" / "meta" / "samples" / "a.json").write_text(json.dumps(record))
    (root / "evaluation" / "report.json").write_text(json.dumps({"probe": {"loss": loss, "windows": [1, 2]}}))
    tensors = {"state.0.exp_avg": np.ones(3, np.float32), "rng.torch": np.full(4, rng, np.uint8)}
    save_file(tensors, str(root / "dynamics" / "step-1" / "optimizer.safetensors"))
    (root / "dynamics" / f"events.out.tfevents.{mtime}").write_bytes(b"x")
    return root


def test_runs_that_differ_only_as_reruns_do_compare_equal(tmp_path, capsys):
    compare = load()
    a, b = run_dir(tmp_path / "a", 1, 7, 0.5), run_dir(tmp_path / "b", 2, 9, 0.5)
    assert compare.main([str(a), str(b)]) == 0
    out = capsys.readouterr().out
    assert "input files' mtimes: 1;" in out and "rng.torch: 1;" in out and "values that differ: 0" in out


def test_a_moved_value_or_a_changed_file_fails_and_is_named(tmp_path, capsys):
    compare = load()
    a, b = run_dir(tmp_path / "a", 1, 7, 0.5), run_dir(tmp_path / "b", 1, 7, 0.25)
    (b / "corpus" / "meta" / "samples" / "a.json").write_text(json.dumps({"files": {}, "frames": 31}))
    assert compare.main([str(a), str(b)]) == 1
    out = capsys.readouterr().out
    assert "probe.loss: 0.5 -> 0.25" in out and "corpus/meta/samples/a.json" in out
