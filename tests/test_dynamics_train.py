"""Training the dynamics model: it learns (beats baselines on held-out windows), resumes exactly, and
runs under 2-process DDP (gloo) with a checkpoint one process can load, on one machine or as two loopback
"nodes"."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest
import torch
from safetensors.torch import load_file

from marionette import training
from marionette.checkpoint import latest_checkpoint, load_checkpoint
from marionette.corpus import Corpus
from marionette.dynamics.config import DynamicsConfig, TrainConfig
from marionette.dynamics.model import DynamicsModel
from marionette.dynamics.train import run, train

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


def test_training_learns_and_records(split_corpus, tmp_path, monkeypatch):
    """Loss halves over 200 steps; the checkpoint holds the run's losses and config; TensorBoard gets the
    terms; the finished run asked again does no work, and asked again under torchrun starts no process.
    (Beating the baselines is shown on the larger dynamics corpus: test_dynamics_control.)"""
    cfg = TrainConfig(preset="tiny", steps=200, batch_size=4, window=32, lr=2e-3, warmup=20, seed=0)
    s = train(split_corpus, tmp_path / "run", cfg, log=lambda *_: None)
    first = sum(r["total"] for r in s["losses"][:10]) / 10
    last = sum(r["total"] for r in s["losses"][-10:]) / 10
    print(f"\nparameters {s['parameters']}; window {s['window']}; train loss (mean of 10 steps) {first:.4f} → {last:.4f}")
    for k in ("action", "root", "body", "drift", "hinge"):
        print(f"  {k}: {s['first'][k]:.4f} → {s['final'][k]:.4f}")
    assert s["steps"] == 200 and s["eval"]["windows"] > 0
    assert last < 0.5 * first
    assert s["final"]["hinge"] == 0.0  # the split corpus has no terrain: every surface is unknown
    ckpt = latest_checkpoint(tmp_path / "run")
    meta = json.loads((ckpt / "meta.json").read_text())
    assert meta["step"] == 200 and len(meta["losses"]) == 200
    assert TrainConfig.from_json(meta["train_config"]) == cfg
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(tmp_path / "run" / "tensorboard"))
    events.Reload()
    assert len(events.Scalars("train/total")) == 200 and events.Scalars("eval/action_accuracy")
    assert events.Scalars("train/total")[-1].value == pytest.approx(s["final"]["total"], rel=1e-6)
    written = (ckpt / "model.safetensors").stat().st_mtime_ns
    again = train(split_corpus, tmp_path / "run", cfg, log=lambda *_: None)  # finished: nothing to do
    assert again["steps"] == 200 and again["checkpoint"] == str(ckpt)
    assert (ckpt / "model.safetensors").stat().st_mtime_ns == written
    monkeypatch.setattr(training, "train_under_torchrun", lambda *a, **k: pytest.fail("a finished run started torchrun"))
    assert run(split_corpus, tmp_path / "run", cfg, nproc=2) == json.loads((tmp_path / "run" / "summary.json").read_text())
    assert training.finished_summary(tmp_path / "run", replace(cfg, lr=1e-3)) is None  # another config: the ranks decide
    assert training.finished_summary(tmp_path / "run", replace(cfg, steps=300)) is None


def test_an_untrained_model_is_copy_last(split_corpus, tmp_path):
    """Zero output heads, the action copy gain and the body anchor's unit gain: before its first step the model's
    held-out action accuracy and body MSE are the copy-last baselines' exactly, so training starts from them."""
    cfg = TrainConfig(preset="tiny", steps=10, batch_size=4, window=32, seed=0)
    s = train(split_corpus, tmp_path / "run", cfg, log=lambda *_: None, stop_at=0)
    ev, base = s["eval"], s["baselines"]
    print(
        f"\nuntrained, {ev['windows']} held-out windows: action accuracy {ev['action_accuracy']:.4f} "
        f"(copy-last {base['copy_last_action_accuracy']:.4f}), body MSE {ev['body_mse']:.5f} (copy-last "
        f"{base['copy_last_body_mse']:.5f}), root MSE {ev['root_mse']:.5f} (constant velocity {base['constant_velocity_root_mse']:.5f})"
    )
    assert s["steps"] == 0 and ev["windows"] > 0
    assert ev["action_accuracy"] == base["copy_last_action_accuracy"]
    assert ev["body_mse"] == base["copy_last_body_mse"]


def test_penetration_hinge_on_recorded_bodies(scanned_corpus):
    """On recorded bodies the hinge is mean ReLU(margin − clearance)² over known key joints (the
    clearances the terrain features hold), and its gradient lifts joints that sink."""
    from marionette.dynamics.data import HeldOutWindows, WindowData
    from marionette.dynamics.normalise import Normaliser
    from marionette.dynamics.train import N_PATCH, PenetrationHinge

    c = Corpus(scanned_corpus)
    nz = Normaliser.from_corpus(c)
    data = WindowData(c, "train", terrain=True, normaliser=nz)
    batch = next(iter(HeldOutWindows(data, 16, 8)))
    f, known = batch.frames, batch.terrain_known
    hinge = PenetrationHinge(c.layout, nz, margin=0.15)
    value = hinge(f.body, f.body, f.root, f.terrain, known)
    clear, ok = f.terrain[..., N_PATCH:], known[..., N_PATCH:]
    expected = torch.where(ok, torch.relu(0.15 - clear.double()) ** 2, 0.0).sum() / ok.sum()
    print(
        f"\nhinge on recorded bodies {value.item():.5f} over {int(ok.sum())} known key joints; "
        f"clearance median {clear[ok].median().item():.3f} m"
    )
    assert ok.sum() > 100
    assert value.item() == pytest.approx(expected.item(), rel=1e-4, abs=1e-7)
    body = f.body.clone().requires_grad_(True)
    hinge(body, f.body, f.root, f.terrain, known).backward()
    assert body.grad.abs().sum() > 0
    # lowering every key joint by 0.5 m (a body sunk into the ground) raises the hinge
    sunk = nz.normalise_body(nz.denormalise_body(f.body.double()) - 0.5 * _up_mask(c, hinge, f.root, nz)).float()
    deep = torch.where(ok, torch.relu(0.15 + 0.5 - clear.double()) ** 2, 0.0).sum() / ok.sum()
    assert hinge(sunk, f.body, f.root, f.terrain, known).item() == pytest.approx(deep.item(), rel=1e-3)
    assert deep > value + 0.1


def _up_mask(c, hinge, root, nz):
    """A body-shaped offset that moves every key joint 1 m along world up (in its root frame)."""
    from marionette import geometry as geo

    raw_root = nz.denormalise_root(root.double())
    out = torch.zeros(*root.shape[:2], len(nz.body_mean), dtype=torch.float64)
    for i, idx, _ in hinge.parts:
        up = geo.rot6d_to_matrix(raw_root[..., 9 * i + 3 : 9 * i + 9])[..., 1, :]  # R[1, :] = up in the root frame
        for row in idx:
            out[..., row] = up
    return out


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
        train(
            split_corpus,
            tmp_path / "split",
            TrainConfig(**{**cfg.to_json(), "betas": (0.9, 0.95), "lr": 5e-4}),
            log=lambda *_: None,
        )


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _two_nodes(args: list[str], env: dict) -> list[subprocess.CompletedProcess]:
    """``marionette train dynamics ARGS --nnodes 2 --node-rank R`` for R = 0, 1 at once on a fresh loopback
    port, each a "node" with its own torchrun; both killed if either is still running after 300 s."""
    marionette = str(Path(sys.executable).with_name("marionette"))
    nodes = ["--nnodes", "2", "--master-addr", "127.0.0.1", "--master-port", str(_free_port())]
    procs = [
        subprocess.Popen(
            [marionette, "train", "dynamics", *args, *nodes, "--node-rank", str(r)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        for r in (0, 1)
    ]
    done = []
    try:
        for p in procs:
            out, err = p.communicate(timeout=300)
            done.append(subprocess.CompletedProcess(p.args, p.returncode, out, err))
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    return done


def test_two_nodes_on_loopback_train_and_resume(split_corpus, tmp_path):
    """Two torchrun "nodes" (``--nnodes 2 --node-rank 0/1``, one process each, a static rendezvous on
    127.0.0.1) train the tiny preset into one shared OUT: rank 0 (node 0) writes the checkpoints, both
    nodes print its summary, the checkpoint loads in one process; rerun from the step-2 checkpoint, both
    nodes resume and repeat the losses. (One machine's ``--nproc 2``, torchrun ``--standalone``, is what the
    train-dynamics deployment test runs.)"""
    out = tmp_path / "nodes"
    args = [str(split_corpus), "--out", str(out), "--preset", "tiny", "--steps", "4", "--batch-size", "4", "--window", "16"]
    args += ["--warmup", "2", "--checkpoint-every", "2", "--nproc", "1", "--no-progress"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "CUDA_VISIBLE_DEVICES": ""}
    runs = _two_nodes(args, env)
    for r in runs:
        assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "batch 4 × 2 ranks" in runs[0].stdout  # rank 0 logs, and the world is both nodes
    printed = [json.loads(r.stdout[r.stdout.find("\n{") + 1 :]) for r in runs]  # the summary rank 0 wrote, on both
    assert printed[0] == printed[1] == json.loads((out / "summary.json").read_text())
    assert printed[0]["steps"] == 4 and printed[0]["checkpoint"].endswith("step-00000004")
    ckpt = latest_checkpoint(out)
    meta = json.loads((ckpt / "meta.json").read_text())
    assert [x["step"] for x in meta["losses"]] == [1, 2, 3, 4]
    weights = load_file(str(ckpt / "model.safetensors"))
    fresh = DynamicsModel(DynamicsConfig.from_json(meta["dynamics_config"]), seed=123)  # the checkpoint loads in one process
    before = {k: v.clone() for k, v in fresh.state_dict().items()}
    load_checkpoint(ckpt, fresh)
    assert all(torch.equal(fresh.state_dict()[k], weights[k]) for k in weights)
    assert any(not torch.equal(before[k], weights[k]) for k in weights)
    # interrupted after step 2: drop the step-4 checkpoint; both nodes rerun resume from step 2 and redo 3 and 4
    shutil.rmtree(ckpt)
    (out / "latest").write_text("step-00000002\n")
    runs = _two_nodes(args, env)
    for r in runs:
        assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "at step 2" in runs[0].stdout and json.loads((out / "summary.json").read_text())["steps"] == 4
    again = json.loads((latest_checkpoint(out) / "meta.json").read_text())
    assert again["losses"] == meta["losses"]  # steps 1, 2 restored; 3, 4 retrained bit for bit
    resumed = load_file(str(latest_checkpoint(out) / "model.safetensors"))
    assert all(torch.equal(resumed[k], weights[k]) for k in weights)
    print(
        f"\n2 nodes × 1 process (gloo, loopback): losses {[round(x['total'], 4) for x in meta['losses']]}; resumed from step 2: identical"
    )
