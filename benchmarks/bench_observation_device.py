"""The observation network on an accelerator: training clips/s and generated frames/s, fp32 against bf16.

    .venv/bin/python benchmarks/bench_observation_device.py [--device cuda] [--steps 50]

Random clips in the model's ranges (RGB in [−1, 1], pose frames in [0, 1]); the tiny preset at the
tests' 5×18×32 (patch 2) and the small preset at its own 17×88×160 (patch 8). Training: AdamW steps of
the rectified-flow loss after 5 warm-up steps; generation: one ``sample_chunk`` of 16 Euler steps for the
whole batch. bf16 is ``torch.autocast`` (weights and optimiser state stay fp32). First line: the largest
difference between a chunk sampled on the CPU and on the device from the same seed (fp32, untrained
weights; the noise is drawn on the CPU, so the two should agree to rounding).
"""

from __future__ import annotations

import argparse
import time

import torch
from common import preamble, table  # noqa: I001  (benchmarks/ on sys.path)

from marionette.observation.config import OBS_PRESETS, ObservationConfig
from marionette.observation.model import VideoDiT, flow_loss, sample_chunk

TINY = ObservationConfig(frames=5, height=18, width_px=32, patch=2, width=96, layers=3, heads=4)


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def throughput(config: ObservationConfig, batch: int, bf16: bool, device: str, steps: int) -> tuple[float, float]:
    """(training clips/s, generated frames/s) of a fresh network on random clips."""
    model = VideoDiT(config).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    g = torch.Generator().manual_seed(0)
    shape = (batch, config.frames, 3, config.height, config.width_px)
    rgb = (torch.rand(shape, generator=g) * 2 - 1).to(device)
    pose = torch.rand(shape, generator=g).to(device)
    autocast = torch.autocast(device.split(":")[0], dtype=torch.bfloat16, enabled=bf16)

    def step() -> None:
        with autocast:
            loss = flow_loss(model, rgb, pose, g)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    for _ in range(5):
        step()
    sync(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    sync(device)
    train = batch * steps / (time.perf_counter() - t0)
    model.eval()
    with autocast:
        sample_chunk(model, pose, rgb[:, 0], 2, g)
        sync(device)
        t0 = time.perf_counter()
        sample_chunk(model, pose, rgb[:, 0], 16, g)
        sync(device)
    return train, batch * (config.frames - 1) / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--steps", type=int, default=50)
    a = ap.parse_args()
    print(preamble(f"Observation network on {a.device}: fp32 against bf16"))
    if a.device.startswith("cuda"):
        print(f"device: {torch.cuda.get_device_name(a.device)}, torch {torch.__version__}\n")
        torch.backends.cuda.matmul.allow_tf32 = False
    g = torch.Generator().manual_seed(3)
    pose, first = torch.rand(1, TINY.frames, 3, *TINY.size, generator=g), torch.rand(1, 3, *TINY.size, generator=g) * 2 - 1
    model = VideoDiT(TINY).eval()
    on_cpu = sample_chunk(model, pose, first, 8, torch.Generator().manual_seed(1))
    on_dev = sample_chunk(model.to(a.device), pose.to(a.device), first.to(a.device), 8, torch.Generator().manual_seed(1)).cpu()
    print(f"sample_chunk, CPU against {a.device} (fp32, 8 steps): max |Δ| {float((on_cpu - on_dev).abs().max()):.2e}\n")
    rows = []
    for name, config, batches in (("tiny", TINY, (4, 64)), ("small", OBS_PRESETS["small"], (4, 32))):
        for batch in batches:
            for bf16 in (False, True):
                train, gen = throughput(config, batch, bf16, a.device, a.steps)
                size = f"{config.frames}×{config.height}×{config.width_px} p{config.patch}"
                rows.append([name, size, batch, "bf16" if bf16 else "fp32", f"{train:.0f}", f"{gen:.0f}"])
    print(table(["preset", "clip", "batch", "dtype", "training clips/s", "generated frames/s (16 steps)"], rows))


if __name__ == "__main__":
    main()
