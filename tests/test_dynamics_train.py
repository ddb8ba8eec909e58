"""Training the dynamics model: it learns (beats baselines on held-out windows), resumes exactly, and
runs under 2-process DDP (gloo) with a checkpoint one process can load."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest
import torch
from safetensors.torch import load_file

from marionette.dynamics.checkpoint import latest_checkpoint, load_checkpoint
from marionette.dynamics.model import DynamicsConfig, DynamicsModel
from marionette.dynamics.train import TrainConfig, train

HELD_OUT = "data_part1/rec0001"  # the recording moved to "test"


@pytest.fixture(scope="module")
def split_corpus(corpus, tmp_path_factory) -> Path:
    """A copy of the session corpus with one recording's segments in the "test" split."""
    out = tmp_path_factory.mktemp("dyntrain") / "corpus"
    shutil.copytree(corpus, out)
    path = out / "meta" / "segments.parquet"
    seg = pq.read_table(path)
    split = pc.if_else(pc.equal(seg["sample"], HELD_OUT), pa.scalar("test"), seg["split"])
    pq.write_table(seg.set_column(seg.schema.get_field_index("split"), "split", split), path)
    assert set(pq.read_table(path)["split"].to_pylist()) == {"train", "test"}
    return out


def test_training_learns_and_beats_baselines(split_corpus, tmp_path):
    cfg = TrainConfig(preset="tiny", steps=200, batch_size=4, window=32, lr=2e-3, warmup=20, seed=0)
    s = train(split_corpus, tmp_path / "run", cfg, log=lambda *_: None)
    first = sum(r["total"] for r in s["losses"][:10]) / 10
    last = sum(r["total"] for r in s["losses"][-10:]) / 10
    ev, base = s["eval"], s["baselines"]
    print(f"\nparameters {s['parameters']}; window {s['window']}, held-out windows {ev['windows']}")
    print(f"train loss (mean of 10 steps) start {first:.4f} → end {last:.4f}")
    for k in ("action", "root", "body", "drift"):
        print(f"  {k}: {s['first'][k]:.4f} → {s['final'][k]:.4f}")
    print(f"next-action accuracy: model {ev['action_accuracy']:.4f}, most-frequent {base['most_frequent_action_accuracy']:.4f}, "
          f"copy-last {base['copy_last_action_accuracy']:.4f}")  # fmt: skip
    print(f"body MSE (normalised): model {ev['body_mse']:.5f}, copy-last {base['copy_last_body_mse']:.5f}")
    print(f"root MSE (normalised): model {ev['root_mse']:.5f}, constant-velocity {base['constant_velocity_root_mse']:.5f}")
    assert s["steps"] == 200 and ev["windows"] > 0
    assert last < 0.5 * first
    assert ev["action_accuracy"] > base["most_frequent_action_accuracy"]
    assert ev["body_mse"] < base["copy_last_body_mse"]
    ckpt = latest_checkpoint(tmp_path / "run")
    meta = json.loads((ckpt / "meta.json").read_text())
    assert meta["step"] == 200 and len(meta["losses"]) == 200
    assert TrainConfig.from_json(meta["train_config"]) == cfg


def test_resume_is_exact(split_corpus, tmp_path):
    cfg = TrainConfig(preset="tiny", steps=12, batch_size=4, window=16, lr=1e-3, warmup=3, checkpoint_every=5, seed=3)
    whole = train(split_corpus, tmp_path / "whole", cfg, log=lambda *_: None)
    half = train(split_corpus, tmp_path / "split", cfg, log=lambda *_: None, stop_at=6)
    assert half["steps"] == 6 and latest_checkpoint(tmp_path / "split").name == "step-00000006"
    resumed = train(split_corpus, tmp_path / "split", cfg, log=lambda *_: None)
    assert resumed["steps"] == 12
    assert [r["total"] for r in resumed["losses"]] == [r["total"] for r in whole["losses"]]  # bit-identical
    assert resumed["losses"] == whole["losses"]
    a = load_file(str(latest_checkpoint(tmp_path / "whole") / "model.safetensors"))
    b = load_file(str(latest_checkpoint(tmp_path / "split") / "model.safetensors"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    print(f"\nresume: 12 losses identical, {whole['losses'][0]['total']:.5f} → {whole['losses'][-1]['total']:.5f}")
    with pytest.raises(ValueError, match="another config"):
        train(split_corpus, tmp_path / "split", TrainConfig(**{**cfg.to_json(), "betas": (0.9, 0.95), "lr": 5e-4}),
              log=lambda *_: None)  # fmt: skip


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_ddp_two_processes_gloo(split_corpus, tmp_path):
    out = tmp_path / "ddp"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "CUDA_VISIBLE_DEVICES": ""}
    cmd = [
        sys.executable, "-m", "torch.distributed.run", "--nnodes", "1", "--nproc-per-node", "2",
        "--master-addr", "127.0.0.1", "--master-port", str(_free_port()),
        "-m", "marionette.dynamics.train", str(split_corpus), "--out", str(out),
        "--preset", "tiny", "--steps", "4", "--batch-size", "4", "--window", "16", "--warmup", "2",
    ]  # fmt: skip
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert sum(line.startswith("step 4 ") for line in r.stdout.splitlines()) == 1  # rank 0 logs alone
    ckpt = latest_checkpoint(out)
    assert ckpt is not None and ckpt.name == "step-00000004"
    meta = json.loads((ckpt / "meta.json").read_text())
    assert len(meta["losses"]) == 4
    fresh = DynamicsModel(DynamicsConfig.from_json(meta["dynamics_config"]), seed=123)
    before = {k: v.clone() for k, v in fresh.state_dict().items()}
    load_checkpoint(ckpt, fresh)
    weights = load_file(str(ckpt / "model.safetensors"))
    assert all(torch.equal(fresh.state_dict()[k], weights[k]) for k in weights)
    assert any(not torch.equal(before[k], weights[k]) for k in weights)
    print(f"\nDDP 2×gloo: losses {[round(x['total'], 4) for x in meta['losses']]}, checkpoint {ckpt.name} loads")
