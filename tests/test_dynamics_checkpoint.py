"""Checkpoints: safetensors + JSON, atomic, exact resume (weights, AdamW state, scheduler, RNG)."""

import json
import math

import pytest
import torch

from marionette import checkpoint as ck


def setup(seed=0):
    torch.manual_seed(seed)
    model = torch.nn.Sequential(torch.nn.Linear(8, 16), torch.nn.GELU(), torch.nn.Linear(16, 4))
    opt = torch.optim.AdamW(model.parameters(), lr=1e-2, weight_decay=0.1)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: min(1.0, (s + 1) / 3) * 0.5 * (1 + math.cos(math.pi * min(s, 20) / 20))
    )
    return model, opt, sched


def train(model, opt, sched, steps):
    losses = []
    for _ in range(steps):
        x = torch.randn(32, 8)  # the batch comes from torch's RNG: resuming must restore it
        loss = ((model(x) - x[:, :4].sin()) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        losses.append(loss.item())
    return losses


def test_resume_continues_the_same_loss_sequence(tmp_path):
    model, opt, sched = setup()
    full = train(model, opt, sched, 12)
    final = {k: v.clone() for k, v in model.state_dict().items()}

    model, opt, sched = setup()
    first = train(model, opt, sched, 5)
    path = ck.save_checkpoint(tmp_path, 5, model, opt, sched, {"config": {"width": 16}, "losses": first})
    assert path.name == "step-00000005" and ck.latest_checkpoint(tmp_path) == path
    train(model, opt, sched, 3)  # the original run goes on and diverges from nothing: it is thrown away

    model2, opt2, sched2 = setup(seed=99)  # other initial weights, other RNG: all must come from the checkpoint
    meta = ck.load_checkpoint(ck.latest_checkpoint(tmp_path), model2, opt2, sched2)
    assert meta["step"] == 5 and meta["config"] == {"width": 16} and meta["losses"] == first
    rest = train(model2, opt2, sched2, 7)
    assert first + rest == full  # bit-identical losses
    for k, v in model2.state_dict().items():
        assert torch.equal(v, final[k]), k
    assert json.loads((path / "meta.json").read_text())["optimizer"]["param_groups"][0]["weight_decay"] == 0.1


def test_a_crash_while_saving_leaves_the_last_checkpoint(tmp_path, monkeypatch):
    model, opt, sched = setup()
    train(model, opt, sched, 2)
    good = ck.save_checkpoint(tmp_path, 2, model, opt, sched)

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(ck, "save_file", boom)
    with pytest.raises(OSError):
        ck.save_checkpoint(tmp_path, 3, model, opt, sched)
    assert ck.latest_checkpoint(tmp_path) == good
    assert sorted(p.name for p in tmp_path.iterdir()) == ["latest", "step-00000002"]  # no half-written directory


def test_loading_checks_what_it_reads(tmp_path):
    model, opt, sched = setup()
    path = ck.save_checkpoint(tmp_path, 1, model, opt)
    other = torch.nn.Linear(8, 4)
    with pytest.raises(ValueError, match="do not fit"):
        ck.load_checkpoint(path, other)
    (path / "model.safetensors").write_bytes(b"\x80\x04 not safetensors, a pickle would start like this")
    with pytest.raises(Exception):  # noqa: B017 - safetensors' own error type; the point is that nothing is unpickled
        ck.load_checkpoint(path, model)
    (tmp_path / "latest").write_text("../elsewhere\n")
    with pytest.raises(ValueError, match="not a complete checkpoint"):
        ck.latest_checkpoint(tmp_path)
