"""``benchmarks/device.sh``: ``--dry`` runs every part on the CPU at tiny sizes and prints its one table, each row
there and each figure a number; without ``--dry``, a torch that cannot reach a GPU is named in one line, not a
traceback."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.corpus  # the bridge part generates, ingests and scans a recording

ROOT = Path(__file__).resolve().parents[1]
NUMBER, TEXT, NUMBER_ON_A_GPU = "number", "text", "number on a GPU"  # NUMBER_ON_A_GPU: "—" on the CPU (no peak)
ROWS = {
    ("bridge", "GL renderer, default EGL"): TEXT,
    ("bridge", "render frames/s, default EGL"): NUMBER,
    ("bridge", "GL renderer, Mesa forced"): TEXT,
    ("bridge", "render frames/s, Mesa forced"): NUMBER,
    ("bridge", "pixels whose codes differ (%)"): NUMBER,
    ("bridge", "pixels whose id differs"): NUMBER,
    ("bridge", "max code difference, height (R)"): NUMBER,
    ("bridge", "max code difference, id (G)"): NUMBER,
    ("bridge", "max code difference, inverse depth (B)"): NUMBER,
    ("bridge", "max code difference, height (R), same id"): NUMBER,
    ("bridge", "max code difference, inverse depth (B), same id"): NUMBER,
    ("dynamics", "parameters"): NUMBER,
    ("dynamics", "tokens/s"): NUMBER,
    ("dynamics", "model TFLOP/s"): NUMBER,
    ("dynamics", "peak bf16 dense TFLOP/s"): NUMBER_ON_A_GPU,
    ("dynamics", "MFU (%)"): NUMBER_ON_A_GPU,
    ("wan", "trainable parameters"): NUMBER,
    ("wan", "s/step"): NUMBER,
    ("wan", "peak memory (GiB)"): NUMBER,
}


def run_script(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHON": sys.executable}
    return subprocess.run(["bash", "benchmarks/device.sh", *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)


def table_rows(stdout: str) -> dict[tuple[str, str], str]:
    """(part, measure) → value of the printed table's body rows."""
    lines = [line for line in stdout.splitlines() if line.startswith("| ")][1:]  # the header row dropped
    return {(c[0], c[1]): c[2] for c in ([cell.strip() for cell in line.strip("|").split("|")] for line in lines)}


@pytest.fixture(scope="module")
def dry():
    return run_script("--dry")


def test_dry_run_prints_every_row_with_numbers(dry):
    assert dry.returncode == 0, dry.stderr
    rows = table_rows(dry.stdout)
    assert set(rows) == set(ROWS)
    for key, kind in ROWS.items():
        value = rows[key]
        if kind == TEXT:
            assert value and value != "failed", key
        elif kind == NUMBER or value != "—":
            assert math.isfinite(float(value)), (key, value)


def test_dry_run_compares_llvmpipe_with_itself_exactly(dry):
    rows = table_rows(dry.stdout)
    assert "llvmpipe" in rows[("bridge", "GL renderer, Mesa forced")]
    assert float(rows[("bridge", "pixels whose codes differ (%)")]) == 0.0
    assert int(rows[("bridge", "pixels whose id differs")]) == 0


def test_without_dry_a_torch_without_cuda_is_named_not_a_traceback():
    torch = pytest.importorskip("torch")
    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU: the script would run in full")
    done = run_script()
    assert done.returncode == 2
    assert "CUDA" in done.stderr and "Traceback" not in done.stderr
    assert done.stdout == ""
