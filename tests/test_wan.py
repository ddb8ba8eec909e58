"""The Wan2.2-Fun-5B-Control adapter on a tiny model built from the real classes, written in the release's
layout (original Wan parameter names and config keys) and loaded back: exactly, strictly, offline, and
relay-generating seeded video."""

from __future__ import annotations

import json
import pickle
import shutil
import socket

import pytest
import torch
from safetensors.torch import load_file, save_file
from torch import nn

from marionette.observation.wan import (
    WanFunControl,
    diffusers_to_wan_name,
    flow_sigmas,
    save_original,
    wan_to_diffusers_name,
)

TRANSFORMER = dict(
    patch_size=(1, 2, 2),
    num_attention_heads=2,
    attention_head_dim=12,
    in_channels=148,
    out_channels=48,
    text_dim=32,
    freq_dim=256,
    ffn_dim=32,
    num_layers=2,
    cross_attn_norm=True,
    qk_norm="rms_norm_across_heads",
    rope_max_seq_len=32,
)
VAE = dict(
    base_dim=3,
    z_dim=48,
    in_channels=12,
    out_channels=12,
    is_residual=True,
    patch_size=2,
    latents_mean=[0.0] * 48,
    latents_std=[1.0] * 48,
    dim_mult=[1, 1, 1, 1],
    num_res_blocks=1,
    scale_factor_spatial=16,
    scale_factor_temporal=4,
    temperal_downsample=[False, True, True],
)
TEXT_LEN = 16


def tiny_modules() -> tuple[nn.Module, nn.Module]:
    """A tiny transformer and VAE of the real classes (``TRANSFORMER``, ``VAE``), in eval mode; diffusers is imported
    here, when a test builds them, not when the suite is collected."""
    from diffusers import AutoencoderKLWan, WanTransformer3DModel

    return WanTransformer3DModel(**TRANSFORMER).eval(), AutoencoderKLWan(**VAE).eval()


def write_backbone(root, transformer: nn.Module, vae: nn.Module, ref_conv: nn.Module | None = None) -> None:
    """``transformer`` (and ``ref_conv``) in the release's layout under ``root``, ``vae`` at ``root / "vae"``."""
    save_original(root, transformer, text_len=TEXT_LEN, ref_conv=ref_conv)
    vae.save_pretrained(root / "vae", safe_serialization=True)


@pytest.fixture
def offline(monkeypatch):
    """Any attempt to open a connection fails the test."""

    def refuse(*args, **kwargs):
        raise AssertionError("the adapter touched the network")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(socket, "getaddrinfo", refuse)


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    """A tiny checkpoint in the release's layout: (directory, source transformer, VAE, ref_conv)."""
    torch.manual_seed(0)
    transformer, vae = tiny_modules()
    ref_conv = nn.Conv2d(48, 24, kernel_size=2, stride=2)
    root = tmp_path_factory.mktemp("wan") / "Wan2.2-Fun-5B-Control"
    write_backbone(root, transformer, vae, ref_conv)
    return root, transformer, vae, ref_conv


@pytest.fixture(scope="module")
def model(release):
    return WanFunControl.from_pretrained(release[0], frames=5)


def inputs(frames: int = 9, size: tuple[int, int] = (32, 32), seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(frames, 3, *size, generator=g), torch.rand(3, *size, generator=g) * 2 - 1


def test_release_layout_has_the_original_names(release):
    root, transformer, _, _ = release
    config = json.loads((root / "config.json").read_text())
    assert {k: config[k] for k in ("dim", "num_heads", "in_dim", "out_dim", "ffn_dim", "num_layers", "text_len")} == {
        "dim": 24,
        "num_heads": 2,
        "in_dim": 148,
        "out_dim": 48,
        "ffn_dim": 32,
        "num_layers": 2,
        "text_len": TEXT_LEN,
    }
    assert config["qk_norm"] is True and config["cross_attn_norm"] is True and config["patch_size"] == [1, 2, 2]
    names = set(load_file(root / "diffusion_pytorch_model.safetensors"))
    for name in (
        "patch_embedding.weight",
        "text_embedding.0.weight",
        "text_embedding.2.bias",
        "time_embedding.0.weight",
        "time_embedding.2.weight",
        "time_projection.1.weight",
        "blocks.0.self_attn.q.weight",
        "blocks.0.self_attn.o.bias",
        "blocks.1.self_attn.norm_k.weight",
        "blocks.0.cross_attn.v.weight",
        "blocks.1.cross_attn.norm_q.weight",
        "blocks.0.norm3.weight",
        "blocks.1.ffn.0.weight",
        "blocks.1.ffn.2.bias",
        "blocks.0.modulation",
        "head.head.weight",
        "head.modulation",
        "ref_conv.weight",
    ):
        assert name in names, name
    assert not any(n.startswith(("condition_embedder", "proj_out", "scale_shift_table")) or ".attn1." in n for n in names)
    diffusers_names = list(transformer.state_dict())  # the mapping is one-to-one over every parameter
    assert [wan_to_diffusers_name(diffusers_to_wan_name(n)) for n in diffusers_names] == diffusers_names
    assert wan_to_diffusers_name("blocks.12.norm3.bias") == "blocks.12.norm2.bias"
    assert wan_to_diffusers_name("blocks.3.cross_attn.k_img.weight") is None  # an image branch has no equivalent here


def test_load_is_exact_and_offline(release, offline):
    root, transformer, vae, ref_conv = release
    m = WanFunControl.from_pretrained(root, frames=5)
    for source, loaded in ((transformer, m.transformer), (vae, m.vae), (ref_conv, m.ref_conv)):
        a, b = source.state_dict(), loaded.state_dict()
        assert a.keys() == b.keys()
        assert all(torch.equal(a[k], b[k]) for k in a)
    g = torch.Generator().manual_seed(3)
    x = torch.randn(1, 148, 3, 4, 4, generator=g)
    t = torch.tensor([[0.0] * 4 + [700.0] * 8])  # per token: frame 0 given
    text = torch.randn(1, TEXT_LEN, 32, generator=g)
    with torch.no_grad():
        assert torch.equal(transformer(x, t, text, return_dict=False)[0], m.transformer(x, t, text, return_dict=False)[0])
    assert m.context.shape == (1, TEXT_LEN, 32) and not m.context.any()  # no text encoder: a zero prompt
    pose, first = inputs()
    assert torch.isfinite(m.generate(pose, first, steps=1, seed=0)).all()


def test_diffusers_layout_loads_too(release, tmp_path):
    _, transformer, _, _ = release
    shutil.copytree(release[0] / "vae", tmp_path / "vae")
    transformer.save_pretrained(tmp_path / "transformer", safe_serialization=True)
    m = WanFunControl.from_pretrained(tmp_path, frames=5)
    assert all(torch.equal(v, m.transformer.state_dict()[k]) for k, v in transformer.state_dict().items())
    assert m.ref_conv is None and m.context.shape == (1, 512, 32)


def test_generate_relays_seeded_chunks(model):
    pose, first = inputs()
    video = model.generate(pose, first, steps=2, seed=0)
    assert video.shape == (9, 3, 32, 32) and video.dtype == torch.float32
    assert torch.isfinite(video).all() and float(video.min()) >= -1.0 and float(video.max()) <= 1.0
    assert torch.equal(video[0], first)
    assert torch.equal(video, model.generate(pose, first, steps=2, seed=0))
    assert not torch.allclose(video[1:], model.generate(pose, first, steps=2, seed=1)[1:])
    assert torch.equal(model.generate(pose, first, chunks=1, steps=2, seed=0), video[:5])  # chunk 1 is the one-chunk video


def test_flow_sigmas():
    s = flow_sigmas(4, 5.0)
    assert s[0] == 1.0 and s[-1] == 0.0 and bool((s[1:] < s[:-1]).all())
    assert torch.allclose(flow_sigmas(4, 1.0), torch.linspace(1, 0, 5))
    assert float(s[2]) == pytest.approx(5 * 0.5 / (1 + 4 * 0.5))  # the shift keeps more steps at high noise


def test_bad_inputs_fail_before_compute(model, monkeypatch):
    def computed(*args, **kwargs):
        raise AssertionError("computed before checking its inputs")

    monkeypatch.setattr(model, "encode", computed)
    monkeypatch.setattr(model, "sample_chunk", computed)
    pose, first = inputs()
    cases = [
        (pose.permute(0, 2, 3, 1), first, "pose video"),  # channels last
        (pose[:8], first, "4k"),
        (pose[:1], first, "at least a chunk"),
        (pose, first[:, :16], "first frame"),
        (*inputs(size=(48, 32)), "multiples of 32"),
        (pose * 2, first, r"outside \[0, 1\]"),
        (pose, first * 3, "outside"),
    ]
    for p, f, match in cases:
        with pytest.raises(ValueError, match=match):
            model.generate(p, f, steps=1)
    with pytest.raises(ValueError, match="3 chunks need 13"):
        model.generate(pose, first, chunks=3, steps=1)


def test_missing_or_renamed_parameter_is_named(release, tmp_path):
    root = tmp_path / "ckpt"
    shutil.copytree(release[0], root)
    path = root / "diffusion_pytorch_model.safetensors"
    weights = load_file(path)
    weights["blocks.1.ffn.two.weight"] = weights.pop("blocks.1.ffn.2.weight")
    save_file(weights, path)
    named = r"diffusion_pytorch_model\.safetensors.*missing \['blocks\.1\.ffn\.2\.weight'\].*unexpected \['blocks\.1\.ffn\.two\.weight'\]"
    with pytest.raises(ValueError, match=named):
        WanFunControl.from_pretrained(root, frames=5)
    del weights["blocks.1.ffn.two.weight"]
    weights["head.modulation"] = weights["head.modulation"][:, :1]
    save_file(weights, path)
    with pytest.raises(ValueError, match=r"wrong shape \['head\.modulation \(1, 1, 24\)"):
        WanFunControl.from_pretrained(root, frames=5)
    config = json.loads((root / "config.json").read_text())
    (root / "config.json").write_text(json.dumps({**config, "sliding_window": 7}))
    with pytest.raises(ValueError, match=r"config\.json.*unknown keys \['sliding_window'\]"):
        WanFunControl.from_pretrained(root, frames=5)


def test_pickled_vae_is_refused_unread(release, tmp_path, monkeypatch):
    def unpickled(*args, **kwargs):
        raise AssertionError("a pickle was loaded")

    monkeypatch.setattr(torch, "load", unpickled)
    monkeypatch.setattr(pickle, "load", unpickled)
    for name in ("config.json", "diffusion_pytorch_model.safetensors"):
        shutil.copy(release[0] / name, tmp_path / name)
    (tmp_path / "Wan2.2_VAE.pth").write_bytes(b"not read")
    with pytest.raises(ValueError, match=r"Wan2\.2_VAE\.pth.*never unpickles.*convert it offline"):
        WanFunControl.from_pretrained(tmp_path)
    (tmp_path / "vae").mkdir()
    shutil.copy(release[0] / "vae" / "config.json", tmp_path / "vae" / "config.json")
    (tmp_path / "vae" / "diffusion_pytorch_model.bin").write_bytes(b"not read")
    with pytest.raises(ValueError, match=r"no diffusion_pytorch_model\.safetensors.*torch pickles"):
        WanFunControl.from_pretrained(tmp_path)


def test_half_precision_keeps_the_float32_modules(release):
    m = WanFunControl.from_pretrained(release[0], frames=5, dtype=torch.bfloat16)
    dtypes = {n: p.dtype for n, p in m.transformer.named_parameters()}
    assert dtypes["blocks.0.attn1.to_q.weight"] == torch.bfloat16 and dtypes["proj_out.weight"] == torch.bfloat16
    assert dtypes["blocks.0.scale_shift_table"] == dtypes["condition_embedder.time_embedder.linear_1.weight"] == torch.float32
    assert {p.dtype for p in m.vae.parameters()} == {torch.float32}
    pose, first = inputs()
    assert torch.isfinite(m.generate(pose, first, steps=1)).all()


def test_the_reference_path_prepends_one_latent_frame_of_tokens(model):
    """``forward_with_reference`` with no reference tokens is the library's forward; with a reference sheet's tokens
    (through the release's ``ref_conv``) the velocity changes and keeps its shape."""
    from marionette.observation.wan import forward_with_reference

    g = torch.Generator().manual_seed(3)
    inp = torch.randn(1, 148, 2, 2, 2, generator=g)  # two latent frames of 2 × 2 latents: one token per frame
    ts = torch.tensor([[0.0, 500.0]])
    t = model.transformer
    with torch.no_grad():
        plain = t(inp, timestep=ts, encoder_hidden_states=model.context, return_dict=False)[0]
        none = forward_with_reference(t, inp, ts, model.context, torch.zeros(1, 0, 24))
        sheet = torch.rand(3, 32, 32, generator=g) * 2 - 1
        ref = model.reference_tokens(sheet)
        with_ref = forward_with_reference(t, inp, ts, model.context, ref)
        other = forward_with_reference(t, inp, ts, model.context, model.reference_tokens(-sheet))
    assert torch.allclose(none, plain, atol=1e-6, rtol=0)
    assert ref.shape == (1, 1, 24) and with_ref.shape == plain.shape
    assert not torch.allclose(with_ref, plain) and not torch.allclose(with_ref, other)
    with pytest.raises(ValueError, match="one latent frame"):
        forward_with_reference(t, inp, ts, model.context, torch.zeros(1, 3, 24))


def test_a_relay_with_references_keeps_a_sheet_of_first_looks(model, release, tmp_path):
    """``generate(references=bands)`` gives every chunk the sheet of each entity's first crop (deterministic, and
    another video than without); a checkpoint without ``ref_conv`` says so."""
    from marionette.bridge.gbuffer import CODE_MAX
    from marionette.observation.references import reference_sheet

    pose, first = inputs()
    ids = torch.zeros(9, 32, 32)
    ids[:, 8:20, 4:10] = 200  # the hunter's band, in every frame
    ids[4:, 10:24, 20:28] = 150  # a monster, from frame 4 on (seen first in a generated frame)
    pose[:, 1] = torch.round(ids / 255 * CODE_MAX) / CODE_MAX
    bands = ((105, 194), (195, 254))
    a = model.generate(pose, first, steps=2, seed=0, references=bands)
    assert torch.equal(a, model.generate(pose, first, steps=2, seed=0, references=bands))
    assert not torch.allclose(a[1:], model.generate(pose, first, steps=2, seed=0)[1:])
    assert torch.equal(a[0], first)
    refs = torch.zeros(2, 4, 8, 8)
    refs[1, :3], refs[1, 3] = 0.5, 1.0
    sheet = reference_sheet(refs, 32, 32)
    assert sheet.shape == (3, 32, 32) and float(sheet[:, :16, 16:].abs().max()) == pytest.approx(0.5)
    assert float(sheet[:, :16, :16].abs().max()) == 0.0 and float(sheet[:, 16:].abs().max()) == 0.0  # unseen: grey
    shutil.copytree(release[0] / "vae", tmp_path / "vae")
    release[1].save_pretrained(tmp_path / "transformer", safe_serialization=True)
    plain = WanFunControl.from_pretrained(tmp_path, frames=5)
    with pytest.raises(ValueError, match="no reference-image path"):
        plain.generate(pose, first, steps=1, references=bands)
