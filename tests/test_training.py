"""The training skeleton: flags generated from a config dataclass (help, defaults, validation), the node
options checked alone and together, the warm-up + cosine schedule, per-step seeds, and the resume check
naming the fields that differ."""

from __future__ import annotations

import argparse
import json
import math

import pytest
import torch

from marionette import knobs, training
from marionette.distributed import Nodes
from marionette.dynamics.config import TrainConfig
from marionette.observation.config import ObservationTrainConfig
from marionette.options import Parser


def _parser(cls) -> argparse.ArgumentParser:
    ap = Parser(prog="t")
    knobs.add_training_arguments(ap, cls)
    return ap


def test_flags_come_from_the_config_fields_with_help_defaults_and_checks(tmp_path, capsys):
    ap = _parser(ObservationTrainConfig)
    text = " ".join(ap.format_help().split())
    for flag in (
        "--preset",
        "--control",
        "--steps",
        "--batch-size",
        "--frames",
        "--reduce",
        "--patch",
        "--lr",
        "--warmup",
        "--seed",
        "--checkpoint-every",
        "--reference-swap",
        "--nproc",
        "--nnodes",
        "--node-rank",
        "--master-addr",
        "--master-port",
        "--out",
        "--progress",
    ):
        assert flag in text
    assert "(default: 1000)" in text and "(default: pose)" in text and "default: the preset's" in text
    a = ap.parse_args(["c", "--out", str(tmp_path), "--steps", "7", "--control", "actions"])
    assert knobs.config_from_args(ObservationTrainConfig, a) == ObservationTrainConfig(steps=7, control="actions")
    for bad in (
        ["--steps", "0"],
        ["--batch-size", "-1"],
        ["--reference-swap", "1.5"],
        ["--control", "x"],
        ["--preset", "huge"],
        ["--lr", "nan"],
        ["--nproc", "0"],
    ):
        with pytest.raises(SystemExit) as exit_:
            ap.parse_args(["c", "--out", str(tmp_path), *bad])
        assert exit_.value.code == 2
        assert bad[0] in capsys.readouterr().err
    with pytest.raises(ValueError, match="frames"):
        knobs.config_from_args(ObservationTrainConfig, ap.parse_args(["c", "--out", str(tmp_path), "--frames", "6"]))


def test_node_flags_are_checked_alone_and_together(tmp_path, capsys):
    """Each node option is refused where it is parsed (exit 2, the problem named), alone or with the others;
    good ones become torchrun's static-rendezvous arguments, one machine keeps its loopback rendezvous."""
    ap = _parser(TrainConfig)
    several = ["--nnodes", "2", "--master-addr", "10.0.0.5", "--master-port", "29500"]
    for bad, said in (
        (["--nnodes", "0"], "--nnodes: must be at least 1, not 0"),
        (["--node-rank", "-1"], "--node-rank: must be at least 0, not -1"),
        ([*several, "--node-rank", "2"], "--node-rank must be at least 0 and below --nnodes (2), not 2"),
        (["--nnodes", "2", "--master-port", "29500"], "--nnodes 2 needs --master-addr"),
        (["--nnodes", "3", "--master-addr", "h"], "--nnodes 3 needs --master-port"),
        (["--master-port", "29500"], "--master-port only with --nnodes > 1"),
        ([*several[:4], "--master-port", "0"], "--master-port: a TCP port runs from 1 to 65535, not 0"),
        ([*several[:4], "--master-port", "65536"], "not 65536"),
        ([*several[:4], "--master-port", "x"], "--master-port: expected an integer, not 'x'"),
        (["--nnodes", "2", "--master-addr", "", "--master-port", "1"], "--master-addr: expected a host name"),
        (["--nnodes", "2", "--master-addr", "10.0.0.5:29500", "--master-port", "1"], "without a port"),
        (["--nnodes", "2", "--master-addr", "tcp://h", "--master-port", "1"], "no scheme, path or spaces"),
    ):
        with pytest.raises(SystemExit) as exit_:
            ap.parse_args(["c", "--out", str(tmp_path), *bad])
        assert exit_.value.code == 2
        assert said in capsys.readouterr().err, bad
    nodes = knobs.nodes_from_args(ap.parse_args(["c", "--out", str(tmp_path), *several, "--node-rank", "1"]))
    assert nodes == Nodes(2, 1, "10.0.0.5", 29500)
    assert nodes.torchrun_arguments(4) == [
        "--nnodes=2",
        "--node-rank=1",
        "--master-addr=10.0.0.5",
        "--master-port=29500",
        "--nproc-per-node=4",
    ]
    one = knobs.nodes_from_args(ap.parse_args(["c", "--out", str(tmp_path)]))
    assert one == Nodes() and one.torchrun_arguments(2) == ["--standalone", "--nproc-per-node=2"]
    with pytest.raises(ValueError, match="--nnodes 2 needs --master-addr and --master-port"):
        Nodes(2, 0)


def test_config_json_then_flags(tmp_path):
    (tmp_path / "c.json").write_text(json.dumps(TrainConfig(steps=5, lr=1e-3).to_json()))
    a = _parser(TrainConfig).parse_args(
        ["c", "--out", "o", "--config", str(tmp_path / "c.json"), "--steps", "9", "--betas", "0.8", "0.9"]
    )
    assert knobs.config_from_args(TrainConfig, a) == TrainConfig(steps=9, lr=1e-3, betas=(0.8, 0.9))
    with pytest.raises(ValueError, match="dropout"):
        TrainConfig(dropout=1.0)


def test_schedule_warms_up_then_decays_to_the_floor():
    f = [training.lr_factor(s, 10, 110, 0.1) for s in range(120)]
    assert f[0] == pytest.approx(0.1) and f[9] == 1.0 and f[10] == 1.0
    assert f[60] == pytest.approx(0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * 0.5)))
    assert f[110] == pytest.approx(0.1) and f[119] == pytest.approx(0.1)
    assert all(a >= b for a, b in zip(f[10:], f[11:]))


def test_noise_seeds_differ_per_step_rank_and_stream():
    seeds = {training.noise_seed(0, s, r, k) for s in range(50) for r in range(4) for k in range(2)}
    assert len(seeds) == 400 and training.noise_seed(3, 7, 1) == training.noise_seed(3, 7, 1)


def test_resume_names_the_fields_that_differ(tmp_path):
    from marionette.checkpoint import save_checkpoint

    model = torch.nn.Linear(2, 2)
    opt = torch.optim.AdamW(model.parameters())
    sched = training.warmup_cosine(opt, 2, 10, 0.1)
    cfg = ObservationTrainConfig(steps=10, reference_swap=0.2)
    save_checkpoint(tmp_path, 3, model, opt, sched, {"train_config": cfg.to_json(), "losses": [{"step": 1}], "evals": []})
    run = training.resume(
        tmp_path, model, opt, sched, {"train_config": ObservationTrainConfig(steps=10, reference_swap=0.2, checkpoint_every=5)}
    )
    assert (run.step, run.started, run.history, run.resumed_from.name) == (3, 3, [{"step": 1}], "step-00000003")
    with pytest.raises(ValueError, match=r"differs in \['steps', 'lr'\].*cannot be extended"):
        training.resume(
            tmp_path, model, opt, sched, {"train_config": ObservationTrainConfig(steps=20, lr=1e-3, reference_swap=0.2)}
        )
