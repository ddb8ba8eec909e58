"""Fine-tuning Wan2.2-Fun-Control: what a step costs, measured on a tiny model here and estimated for the 5B.

    .venv/bin/python benchmarks/bench_wan_train.py [--steps 20]

Measured (this machine): ``marionette.observation.wan_train``'s loss and an AdamW step on a small random model
built from the real classes (4 blocks of width 128), full fine-tuning against LoRA rank 16, with and without
gradient checkpointing, at 9 × 64 × 128 frames (3 latent frames, 4 × 8 latent pixels), batch 2: steps/s.

Estimated (labelled as such, no accelerator used): the 5B configuration's parameter count (the real class on the
meta device, so exact) and the memory one GPU holds per sample: full fine-tuning keeps fp32 weights, gradients
and AdamW's two moments (16 B a parameter, divided over FSDP's shards), LoRA the frozen backbone in bf16 (2 B a
parameter) and its adapters like the full case; activations are Korthikanti et al.'s 34·s·h bytes per block in
bf16 with a fused attention (s tokens, h width), and under gradient checkpointing each block's input (2·s·h)
plus one block recomputed.
"""

from __future__ import annotations

import argparse
import time

import torch
from common import preamble, table  # noqa: I001  (benchmarks/ on sys.path)
from diffusers import WanTransformer3DModel

from marionette.observation.wan_train import add_lora, flow_batch, flow_loss

SMALL = dict(
    patch_size=(1, 2, 2), num_attention_heads=4, attention_head_dim=32, in_channels=148, out_channels=48, text_dim=64,
    freq_dim=256, ffn_dim=256, num_layers=4, cross_attn_norm=True, qk_norm="rms_norm_across_heads", rope_max_seq_len=64,
)  # fmt: skip
# Wan2.2-TI2V-5B's transformer with Fun-Control's 148 input channels (docs/notes/wan2.2-fun-control.md)
FIVE_B = dict(
    patch_size=(1, 2, 2), num_attention_heads=24, attention_head_dim=128, in_channels=148, out_channels=48, text_dim=4096,
    freq_dim=256, ffn_dim=14336, num_layers=30, cross_attn_norm=True, qk_norm="rms_norm_across_heads", rope_max_seq_len=1024,
)  # fmt: skip


def steps_per_second(lora: int, checkpointing: bool, steps: int) -> tuple[float, int]:
    torch.manual_seed(0)
    model = WanTransformer3DModel(**SMALL)
    if lora:
        model.requires_grad_(False)
        model = add_lora(model, lora, float(lora), 0)
    if checkpointing:
        (model.base_model.model if lora else model).enable_gradient_checkpointing()
    model.train()
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=1e-4)
    g = torch.Generator().manual_seed(0)
    latents = [{k: torch.randn(48, 3, 4, 8, generator=g) for k in ("x0", "control", "masked")} for _ in range(4)]
    context = torch.zeros(1, 16, SMALL["text_dim"])

    def step() -> None:
        inp, per_frame, target, _ = flow_batch(latents, [0, 1], g, 5.0, 4)
        loss = flow_loss(model, SMALL["patch_size"], context, inp, per_frame, target, False)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    for _ in range(3):
        step()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    return steps / (time.perf_counter() - t0), sum(p.numel() for p in params)


def estimate(params: int, frames: int, height: int, width: int, shards: int) -> list[str]:
    tokens = (1 + (frames - 1) // 4) * (height // 32) * (width // 32)
    h, layers = FIVE_B["num_attention_heads"] * FIVE_B["attention_head_dim"], FIVE_B["num_layers"]
    act = 34 * tokens * h * layers
    act_ckpt = 2 * tokens * h * layers + 34 * tokens * h
    lora_params = (
        layers * 16 * (4 * (h + h) * 2 + (h + FIVE_B["ffn_dim"]) * 2)
    )  # rank 16 on q, k, v, o of both attentions and the FFN
    full_state, lora_state = 16 * params / shards, 2 * params / shards + 16 * lora_params
    gib = lambda b: f"{b / 2**30:.1f}"  # noqa: E731
    return [
        f"{frames}×{height}×{width}",
        f"{tokens:,}",
        str(shards),
        gib(full_state + act),
        gib(full_state + act_ckpt),
        gib(lora_state + act),
        gib(lora_state + act_ckpt),
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=20)
    a = ap.parse_args()
    if a.steps < 1:
        ap.error("--steps must be at least 1")
    rows = []
    for lora in (0, 16):
        for ckpt in (False, True):
            sps, n = steps_per_second(lora, ckpt, a.steps)
            rows.append(["full" if not lora else f"LoRA rank {lora}", "on" if ckpt else "off", f"{n:,}", f"{sps:.2f}"])
    print(preamble("Wan fine-tuning: a small model's steps/s on this machine (measured)"))
    print(table(["weights trained", "gradient checkpointing", "trainable parameters", "steps/s"], rows))
    with torch.device("meta"):
        params = sum(p.numel() for p in WanTransformer3DModel(**FIVE_B).parameters())
    print(f"\n5B configuration: {params:,} parameters (counted on the meta device). ESTIMATES, not measurements:")
    rows = [estimate(params, f, hh, w, s) for f, hh, w in ((81, 704, 1280), (81, 352, 640), (41, 704, 1280)) for s in (1, 8)]
    head = ["frames×H×W", "tokens", "FSDP shards", "full GiB", "full + ckpt GiB", "LoRA GiB", "LoRA + ckpt GiB"]
    print(table(head, rows))


if __name__ == "__main__":
    main()
