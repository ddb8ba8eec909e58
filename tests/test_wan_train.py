"""Fine-tuning Wan2.2-Fun-Control on a tiny model built from the real classes (test_wan's): the latent
cache is written once and read after, full fine-tuning and LoRA both lower the held-out flow loss, a resumed run
continues the same loss sequence, and the finished run's model loads with ``WanFunControl.from_pretrained`` and
generates; in two processes under DDP and under FSDP, which trains as DDP does, resumes exactly and checkpoints
whole tensors that one process loads."""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import replace

import av
import numpy as np
import pytest
import torch
from safetensors.torch import load_file
from test_wan import TEXT_LEN, tiny_modules, write_backbone
from torch import nn

from marionette.bridge.gbuffer import GBufferMeta, write_gbuffer
from marionette.checkpoint import load_checkpoint
from marionette.cli import main as cli
from marionette.observation.config import WanTrainConfig
from marionette.observation.generate import write_image
from marionette.observation.wan import WanFunControl, save_original
from marionette.observation.wan_train import Trainable, crop_box, train, trainable_transformer

# 9-frame windows (3 latent frames), the follow corpus's 36×64 chunks cropped to 32×64 (2×4 latents): 10 windows per
# 81-frame chunk; 4 train chunks, 2 held out
BASE = dict(steps=40, batch_size=4, frames=9, lr=2e-3, warmup=5, max_chunks=4)


@pytest.fixture(scope="module")
def backbone(tmp_path_factory):
    """A tiny Wan2.2-Fun-Control checkpoint in the release's layout."""
    torch.manual_seed(0)
    root = tmp_path_factory.mktemp("wan-backbone") / "Wan2.2-Fun-5B-Control"
    write_backbone(root, *tiny_modules())
    return root


@pytest.fixture(scope="module")
def full(follow_corpus, backbone, tmp_path_factory):
    out = tmp_path_factory.mktemp("wan-full")
    return out, train(follow_corpus, out, WanTrainConfig(backbone=str(backbone), **BASE), log=lambda *_: None)


def _losses(summary: dict) -> tuple[float, float]:
    return summary["evals"][0]["held_out_loss"], summary["evals"][-1]["held_out_loss"]


def test_full_fine_tuning_lowers_the_held_out_loss_and_its_model_generates(full, backbone):
    out, s = full
    first, last = _losses(s)
    print(f"\nfull fine-tuning: held-out flow loss {first:.4f} → {last:.4f} over {s['steps']} steps, {s['windows']} windows")
    assert s["windows"] == 40 and s["held_out"] > 0 and s["held_out_split"] == "test"
    assert last < 0.8 * first
    model = WanFunControl.from_pretrained(out / "model", frames=9)
    original = WanFunControl.from_pretrained(backbone, frames=9)
    ref = dict(original.transformer.named_parameters())
    still = {n for n, p in model.transformer.named_parameters() if torch.equal(p, ref[n])}
    # every weight trained but the text embedder's input layer, which sees only the fixed (zero) context
    assert still == {"condition_embedder.text_embedder.linear_1.weight"}
    pose, first_frame = torch.rand(17, 3, 32, 64), torch.rand(3, 32, 64) * 2 - 1
    video = model.generate(pose, first_frame, steps=2, seed=0)
    assert video.shape == (17, 3, 32, 64) and torch.isfinite(video).all()
    assert torch.equal(video, model.generate(pose, first_frame, steps=2, seed=0))


def test_the_latent_cache_is_written_once(full, follow_corpus, backbone, tmp_path):
    _, s = full
    assert s["encoded"] == s["windows"] + s["held_out"] and s["reused"] == 0
    again = train(follow_corpus, tmp_path, WanTrainConfig(backbone=str(backbone), **{**BASE, "steps": 1}), log=lambda *_: None)
    assert again["encoded"] == 0 and again["reused"] == s["windows"] + s["held_out"]
    files = list((follow_corpus / "derived" / "wan-latents").rglob("*.safetensors"))
    assert len(files) == s["encoded"] and all(set(load_file(f)) == {"x0", "control", "masked"} for f in files)


def test_lora_trains_only_its_adapters_and_merges_into_the_model(follow_corpus, backbone, tmp_path):
    config = WanTrainConfig(backbone=str(backbone), lora_rank=4, **{**BASE, "lr": 1e-2})  # adapters take a larger step
    s = train(follow_corpus, tmp_path, config, log=lambda *_: None)
    first, last = _losses(s)
    print(f"\nLoRA rank 4: held-out flow loss {first:.4f} → {last:.4f}, {s['trainable_parameters']:,} trainable parameters")
    assert last < 0.9 * first
    meta = json.loads((tmp_path / (tmp_path / "latest").read_text().strip() / "meta.json").read_text())
    from diffusers import WanTransformer3DModel
    from test_wan import TRANSFORMER

    total = sum(p.numel() for p in WanTransformer3DModel(**TRANSFORMER).parameters())
    assert meta["names"] and all(".lora_A." in n or ".lora_B." in n for n in meta["names"])
    assert s["trainable_parameters"] < 0.25 * total  # the checkpoint holds the adapters, not the backbone
    base = WanFunControl.from_pretrained(backbone, frames=9).transformer.state_dict()
    merged = WanFunControl.from_pretrained(tmp_path / "model", frames=9).transformer.state_dict()
    changed = {k for k in base if not torch.equal(base[k], merged[k])}
    assert changed and all(
        k.endswith(".weight") and any(t in k for t in ("to_q", "to_k", "to_v", "to_out", "ffn")) for k in changed
    )


def test_a_resumed_run_continues_the_same_loss_sequence(follow_corpus, backbone, tmp_path):
    config = WanTrainConfig(backbone=str(backbone), lora_rank=2, **{**BASE, "steps": 12})
    whole = train(follow_corpus, tmp_path / "whole", config, log=lambda *_: None)
    train(follow_corpus, tmp_path / "cut", config, log=lambda *_: None, stop_at=5)
    resumed = train(follow_corpus, tmp_path / "cut", config, log=lambda *_: None)
    assert [r["loss"] for r in resumed["losses"]] == [r["loss"] for r in whole["losses"]]
    with pytest.raises(ValueError, match="differs in \\['lr'\\]"):
        train(follow_corpus, tmp_path / "cut", replace(config, lr=1e-3), log=lambda *_: None)


def test_bad_configs_and_crops_are_named(monkeypatch, capsys):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="device: cuda, and this torch sees no CUDA GPU"):
        WanTrainConfig(backbone="x", device="cuda")
    assert cli(["train", "wan", "corpus", "--out", "out", "--backbone", "x", "--device", "cuda", "--nproc", "2"]) == 2
    assert "no CUDA GPU" in capsys.readouterr().err  # refused before anything is launched or read
    with pytest.raises(ValueError, match="backbone"):
        WanTrainConfig()
    with pytest.raises(ValueError, match="4k \\+ 1"):
        WanTrainConfig(backbone="x", frames=8)
    with pytest.raises(ValueError, match="lora_rank"):
        WanTrainConfig(backbone="x", lora_rank=-1)
    assert crop_box((36, 64), 32) == (2, 0, 32, 64) and crop_box((704, 1280), 32) == (0, 0, 704, 1280)
    with pytest.raises(ValueError, match="smaller than one latent patch"):
        crop_box((18, 32), 32)


def wan_argv(corpus, backbone, out, *flags: str) -> list[str]:
    """``marionette train wan`` of a tiny run: 9-frame windows of the first chunk (10 of them, and 10 held out)."""
    argv = ["train", "wan", str(corpus), "--out", str(out), "--backbone", str(backbone), "--no-progress"]
    return [*argv, "--frames", "9", "--max-chunks", "1", *flags]


LORA_FLAGS = ("--steps", "2", "--lora-rank", "2", "--bf16", "--gradient-checkpointing")


@pytest.fixture(scope="module")
def ddp_lora(follow_corpus, backbone, tmp_path_factory):
    """Two LoRA steps of the command in two processes under torchrun (DDP, gloo): its training directory."""
    out = tmp_path_factory.mktemp("wan-ddp")
    assert cli([*wan_argv(follow_corpus, backbone, out, *LORA_FLAGS), "--nproc", "2"]) == 0
    return out


def test_the_command_trains_under_ddp_and_generate_paints_with_the_result(ddp_lora, follow_corpus, backbone, tmp_path):
    assert (ddp_lora / "model" / "config.json").is_file() and (ddp_lora / "model" / "vae" / "config.json").is_file()
    assert json.loads((ddp_lora / "summary.json").read_text())["steps"] == 2
    with pytest.raises(SystemExit):
        cli([*wan_argv(follow_corpus, backbone, tmp_path, *LORA_FLAGS), "--lora-rank", "-1"])
    # `marionette generate` paints with the fine-tuned model at the pose video's size, in its 9-frame chunks
    rng = np.random.default_rng(0)
    meta = GBufferMeta(h_min=0.0, h_max=10.0, z_near=0.3, z_far=100.0, width=64, height=32, fps=20.0)
    write_gbuffer(tmp_path / "pose.mkv", [rng.integers(0, 1024, (32, 64, 3), dtype=np.uint16) for _ in range(17)], meta)
    write_image(tmp_path / "first.png", rng.integers(0, 256, (32, 64, 3), dtype=np.uint8))
    paint = [
        "generate",
        str(ddp_lora / "model"),
        "--pose",
        str(tmp_path / "pose.mkv"),
        "--first-frame",
        str(tmp_path / "first.png"),
    ]
    assert cli([*paint, "--out", str(tmp_path / "painted.mp4"), "--steps", "2"]) == 0
    with av.open(str(tmp_path / "painted.mp4")) as c:
        frames = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
    assert len(frames) == 17 and frames[0].shape == (32, 64, 3)


def read_checkpoint(ckpt) -> tuple[dict, dict, dict]:
    """A checkpoint's weights, its optimizer tensors (the RNG state left out) and its meta."""
    optimizer = {k: v for k, v in load_file(ckpt / "optimizer.safetensors").items() if k != "rng.torch"}
    return load_file(ckpt / "model.safetensors"), optimizer, json.loads((ckpt / "meta.json").read_text())


def losses(meta: dict) -> list[float]:
    return [round(r["loss"], 5) for r in meta["losses"]]


def test_lora_trains_under_fsdp_as_under_ddp(ddp_lora, follow_corpus, backbone, tmp_path):
    """``--fsdp`` with LoRA (frozen and trained weights in one unit), bf16 and gradient checkpointing: the losses, the
    gradient norms (clipped over the shards), the checkpoint (whole tensors, the same names) and the exported model
    are DDP's, to float rounding."""
    assert cli([*wan_argv(follow_corpus, backbone, tmp_path, *LORA_FLAGS), "--fsdp", "--nproc", "2"]) == 0
    weights, optimizer, meta = read_checkpoint(tmp_path / "step-00000002")
    ddp_weights, ddp_optimizer, ddp_meta = read_checkpoint(ddp_lora / "step-00000002")
    print(f"\nLoRA under FSDP: losses {losses(meta)}, under DDP {losses(ddp_meta)}")
    assert meta["names"] == ddp_meta["names"] and all(".lora_A." in n or ".lora_B." in n for n in meta["names"])
    for key in ("loss", "grad_norm"):
        assert [r[key] for r in meta["losses"]] == pytest.approx([r[key] for r in ddp_meta["losses"]], rel=1e-5)
    for mine, theirs in ((weights, ddp_weights), (optimizer, ddp_optimizer)):
        assert mine.keys() == theirs.keys()
        for k in mine:
            assert mine[k].shape == theirs[k].shape and torch.allclose(mine[k], theirs[k], rtol=1e-5, atol=1e-7), k
    exported = load_file(tmp_path / "model" / "diffusion_pytorch_model.safetensors")
    ddp_exported = load_file(ddp_lora / "model" / "diffusion_pytorch_model.safetensors")
    assert exported.keys() == ddp_exported.keys()
    assert all(torch.allclose(exported[k], ddp_exported[k], rtol=1e-5, atol=1e-7) for k in exported)


@pytest.fixture(scope="module")
def fsdp_runs(follow_corpus, backbone, tmp_path_factory):
    """``--fsdp`` in two processes, every weight and the reference path training (bf16, gradient checkpointing): the
    backbone it started from with its reference projection, the whole 3-step run (a checkpoint every step) and a run
    resumed under FSDP from the whole run's step-2 checkpoint."""
    tmp_path = tmp_path_factory.mktemp("wan-fsdp")
    root = tmp_path / "Wan2.2-Fun-5B-Control"
    torch.manual_seed(0)
    ref_conv = nn.Conv2d(48, 24, kernel_size=2, stride=2)
    save_original(root, WanFunControl.from_pretrained(backbone, frames=9).transformer, text_len=TEXT_LEN, ref_conv=ref_conv)
    shutil.copytree(backbone / "vae", root / "vae")  # the backbone's VAE: its latent cache
    corpus = shutil.copytree(follow_corpus, tmp_path / "corpus")  # its reference sheets' cache stays out of the shared one
    flags = ("--steps", "3", "--lr", "2e-3", "--warmup", "1", "--references", "--bf16", "--gradient-checkpointing", "--fsdp")
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    assert cli([*wan_argv(corpus, root, whole, *flags), "--checkpoint-every", "1", "--nproc", "2"]) == 0
    cut.mkdir()
    shutil.copytree(whole / "step-00000002", cut / "step-00000002")  # as if the run had stopped after step 2
    (cut / "latest").write_text("step-00000002\n")
    assert cli([*wan_argv(corpus, root, cut, *flags), "--nproc", "2"]) == 0
    return root, ref_conv, whole, cut


def test_the_command_trains_under_fsdp_and_resumes_exactly(fsdp_runs):
    """A run resumed under FSDP from its step-2 checkpoint ends in the same losses and bit-identical weights and AdamW
    state; every rank evaluated the held-out loss, which fell."""
    _, _, whole, cut = fsdp_runs
    weights, optimizer, meta = read_checkpoint(whole / "step-00000003")
    resumed_weights, resumed_optimizer, resumed_meta = read_checkpoint(cut / "step-00000003")
    print(f"\nfull fine-tuning under FSDP: losses {losses(meta)}, resumed at step 2 {losses(resumed_meta)}")
    assert len(meta["losses"]) == 3 and all(math.isfinite(r["loss"]) and r["grad_norm"] > 0 for r in meta["losses"])
    evals = json.loads((whole / "summary.json").read_text())["evals"]  # every rank evaluated (a forward is collective)
    print(f"held-out flow loss {evals[0]['held_out_loss']:.4f} → {evals[-1]['held_out_loss']:.4f}")
    assert [e["step"] for e in evals] == [0, 3] and evals[1]["held_out_loss"] < 0.95 * evals[0]["held_out_loss"]
    assert resumed_meta["losses"] == meta["losses"]
    assert resumed_weights.keys() == weights.keys() and all(torch.equal(resumed_weights[k], weights[k]) for k in weights)
    assert resumed_optimizer.keys() == optimizer.keys()
    assert all(torch.equal(resumed_optimizer[k], optimizer[k]) for k in optimizer)


def test_one_process_loads_the_fsdp_checkpoint_and_its_model_generates(fsdp_runs):
    """The FSDP checkpoint's tensors are whole: one process loads them into the unsharded model, the exported model
    holds them, and ``generate`` paints with it."""
    root, ref_conv, whole, _ = fsdp_runs
    weights, optimizer, meta = read_checkpoint(whole / "step-00000003")
    # whole tensors: one process loads the checkpoint into the unsharded model, and the exported model holds them
    config = WanTrainConfig.from_json(meta["train_config"])
    module = trainable_transformer(WanFunControl.from_pretrained(root, frames=9), config, torch.device("cpu"))
    trainable = Trainable(module)
    opt = torch.optim.AdamW(trainable.parameters())
    load_checkpoint(whole / "step-00000003", trainable, opt)
    assert trainable.names == meta["names"] and meta["names"][-2:] == ["ref_conv.weight", "ref_conv.bias"]
    assert all(optimizer[f"state.{i}.exp_avg"].shape == p.shape for i, p in enumerate(trainable.params))
    assert opt.state_dict()["state"][0]["exp_avg"].shape == trainable.params[0].shape
    model = WanFunControl.from_pretrained(whole / "model", frames=9)
    exported = {f"transformer.{n}": p for n, p in model.transformer.named_parameters()}
    exported |= {f"ref_conv.{n}": p for n, p in model.ref_conv.named_parameters()}
    original = dict(WanFunControl.from_pretrained(root, frames=9).transformer.named_parameters())
    for i, name in enumerate(meta["names"]):
        assert torch.equal(exported[name], weights[f"params.{i}"]) and torch.equal(trainable.params[i], weights[f"params.{i}"])
    assert not torch.equal(model.ref_conv.weight, ref_conv.weight)
    assert not torch.equal(model.transformer.blocks[0].attn1.to_q.weight, original["blocks.0.attn1.to_q.weight"])
    bands = json.loads((whole / "model" / "marionette-wan.json").read_text())["reference_bands"]
    pose, first_frame = torch.rand(17, 3, 32, 64), torch.rand(3, 32, 64) * 2 - 1
    video = model.generate(pose, first_frame, steps=2, seed=0, references=[tuple(b) for b in bands])
    assert video.shape == (17, 3, 32, 64) and torch.isfinite(video).all()


def test_training_with_references_trains_the_reference_path_and_generate_relays_it(follow_corpus, tmp_path):
    """``references``: every window carries its sheet of first looks (cached apart, once), ``ref_conv`` trains with
    the transformer, the held-out loss falls, and the exported model's settings make ``marionette generate`` relay
    a sheet (``--no-references``: another video)."""
    torch.manual_seed(0)
    root = tmp_path / "Wan2.2-Fun-5B-Control"
    ref_conv = nn.Conv2d(48, 24, kernel_size=2, stride=2)
    write_backbone(root, *tiny_modules(), ref_conv)
    config = WanTrainConfig(backbone=str(root), references=True, **BASE)
    s = train(follow_corpus, tmp_path / "run", config, log=lambda *_: None)
    first, last = _losses(s)
    print(f"\nwith references: held-out flow loss {first:.4f} → {last:.4f} over {s['steps']} steps, {s['windows']} windows")
    assert last < 0.8 * first
    files = list((follow_corpus / "derived" / "wan-latents").glob("*-refs/*.safetensors"))
    assert len(files) == s["encoded"] == s["windows"] + s["held_out"]
    assert all(set(load_file(f)) == {"x0", "control", "masked", "ref"} for f in files)
    again = train(follow_corpus, tmp_path / "again", replace(config, steps=1), log=lambda *_: None)
    assert again["encoded"] == 0
    settings = json.loads((tmp_path / "run" / "model" / "marionette-wan.json").read_text())
    assert settings["reference_bands"] == [[60, 99], [105, 194], [195, 254]]
    trained = WanFunControl.from_pretrained(tmp_path / "run" / "model", frames=9)
    assert not torch.equal(trained.ref_conv.weight, ref_conv.weight)
    rng = np.random.default_rng(0)
    meta = GBufferMeta(h_min=0.0, h_max=10.0, z_near=0.3, z_far=100.0, width=64, height=32, fps=20.0)
    codes = [rng.integers(0, 1024, (32, 64, 3), dtype=np.uint16) for _ in range(17)]
    for c in codes:
        c[8:20, 4:14, 1] = round(200 / 255 * 1023)  # a hunter's bones in every frame
    write_gbuffer(tmp_path / "pose.mkv", codes, meta)
    write_image(tmp_path / "first.png", rng.integers(0, 256, (32, 64, 3), dtype=np.uint8))
    paint = ["generate", str(tmp_path / "run" / "model"), "--pose", str(tmp_path / "pose.mkv")]
    paint += ["--first-frame", str(tmp_path / "first.png"), "--steps", "2"]
    assert cli([*paint, "--out", str(tmp_path / "with.mp4")]) == 0
    assert cli([*paint, "--out", str(tmp_path / "without.mp4"), "--no-references"]) == 0
    assert (tmp_path / "with.mp4").read_bytes() != (tmp_path / "without.mp4").read_bytes()
    with pytest.raises(ValueError, match="no ref_conv"):
        train(follow_corpus, tmp_path / "none", replace(config, backbone=str(backbone_dir(tmp_path))), log=lambda *_: None)


def backbone_dir(tmp_path):
    """A tiny backbone without a reference path."""
    root = tmp_path / "plain"
    write_backbone(root, *tiny_modules())
    return root
