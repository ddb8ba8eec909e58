"""Does the observation model follow the pose? Pose control against the pixel-AR baseline, short and long horizons,
and silhouettes under a swapped pose video.

    .venv/bin/python benchmarks/bench_observation_follow.py [--steps 1000,3000] [--device cuda] [--jitter 0,0.5]

Data: the benchmark corpus of ``bench_observation.py`` with its terrain scanned first (so the pose
frames carry terrain height and depth, not only bones); every 81-frame chunk at 18×32. Models: the tiny
video DiT (5-frame clips, patch 2, batch 8, lr 1e-3, warm-up 20, cosine), trained on the train split's
chunks with the recorded first frame (``jitter`` > 0: with that probability the conditioning first frame
is a frame from a random time of the same chunk, the targets unchanged — reference-frame augmentation),
and the pixel-AR baseline (``control="actions"``). Every figure is on the held-out recording, 16 Euler steps:

- short: mean |generated − recorded| over frames 1–4 of clips starting at 0, 20, 40, 60 of each chunk;
- long: the same over a whole chunk relayed from its first frame (20 chunks of 5 frames);
- copy: repeating the first frame, over the same frames;
- pose follows: first frame of chunk A, pose frames of chunk B (every ordered pair, starts 0 and 40); the
  silhouettes of generated frames 1–4, read by a small convolutional segmenter trained on every recorded
  frame against the bridge's id mask (its IoU on the recorded held-out frames printed as the ceiling), and
  their IoU with B's id masks and with A's. A model that follows the pose scores higher against B.
"""

from __future__ import annotations

import argparse
import itertools
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from common import preamble, table  # noqa: I001  (benchmarks/ on sys.path)
from torch import nn

from marionette.observation.data import ClipSource
from marionette.observation.model import ObservationConfig, VideoDiT, flow_loss, sample_chunk

T, SIZE, STARTS = 5, (18, 32), (0, 20, 40, 60)


def load(corpus: Path, device: str) -> dict[str, torch.Tensor]:
    out = {}
    for split in ("train", "test"):
        chunks = [c for c in ClipSource(corpus, split, T, SIZE, actions=True).chunks() if len(c.rgb) == 81]
        out[f"{split}_rgb"] = torch.stack([c.rgb for c in chunks]).to(device)
        out[f"{split}_pose"] = torch.stack([c.pose for c in chunks]).to(device)
        out[f"{split}_actions"] = torch.stack([c.actions for c in chunks]).to(device)
    return out


def bodies(pose: torch.Tensor) -> torch.Tensor:
    """(…, 3, H, W) pose frames → (…, 1, H, W) 1 where a bone is drawn."""
    return (pose.narrow(-3, 1, 1) > 0.5 / 255).float()


def iou(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a * b).sum() / ((a + b) > 0).float().sum().clamp(min=1))


def segmenter(d: dict[str, torch.Tensor], device: str, steps: int = 2000) -> nn.Module:
    """A small dilated CNN: RGB frame → bone-silhouette logits, fitted to every recorded frame's id mask."""
    torch.manual_seed(0)
    rgb = torch.cat([d["train_rgb"], d["test_rgb"]]).flatten(0, 1)
    mask = bodies(torch.cat([d["train_pose"], d["test_pose"]])).flatten(0, 1)
    net = nn.Sequential(nn.Conv2d(3, 32, 3, padding=1), nn.GELU(), nn.Conv2d(32, 32, 3, padding=2, dilation=2), nn.GELU(),
                        nn.Conv2d(32, 32, 3, padding=4, dilation=4), nn.GELU(), nn.Conv2d(32, 32, 3, padding=1), nn.GELU(),
                        nn.Conv2d(32, 1, 1)).to(device)  # fmt: skip
    opt = torch.optim.Adam(net.parameters(), 3e-3)
    weight = ((1 - mask.mean()) / mask.mean()).sqrt()
    g = torch.Generator().manual_seed(0)
    for _ in range(steps):
        idx = torch.randint(0, len(rgb), (64,), generator=g).to(device)
        loss = F.binary_cross_entropy_with_logits(net(rgb[idx]), mask[idx], pos_weight=weight)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return net.eval().requires_grad_(False)


def train(d: dict[str, torch.Tensor], control: str, steps: int, jitter: float, device: str, batch: int = 8) -> VideoDiT:
    vocab = tuple(int(d["train_actions"][..., i].max()) + 8 for i in range(d["train_actions"].shape[-1]))
    c = ObservationConfig(frames=T, height=SIZE[0], width_px=SIZE[1], patch=2, width=96, layers=3, heads=4, control=control,
                          vocab_sizes=vocab if control == "actions" else ())  # fmt: skip
    model = VideoDiT(c).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3, betas=(0.9, 0.99), weight_decay=0.0)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: min((s + 1) / 20, 0.1 + 0.45 * (1 + np.cos(np.pi * min(s / steps, 1)))))
    g, rng = torch.Generator().manual_seed(0), np.random.default_rng(0)
    n = len(d["train_rgb"])
    for _ in range(steps):
        ci, st = rng.integers(0, n, batch), rng.integers(0, 81 - T + 1, batch)
        rgb = torch.stack([d["train_rgb"][i, j : j + T] for i, j in zip(ci, st)])
        key = "train_pose" if control == "pose" else "train_actions"
        ctrl = torch.stack([d[key][i, j : j + T] for i, j in zip(ci, st)])
        ref = rng.integers(0, 81, batch)
        for b in np.flatnonzero(rng.random(batch) < jitter):
            rgb[b, 0] = d["train_rgb"][ci[b], ref[b]]
        loss = flow_loss(model, rgb, ctrl, g)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
    return model.eval()


def evaluate(model: VideoDiT, d: dict[str, torch.Tensor], seg: nn.Module) -> dict[str, float]:
    key = "test_pose" if model.config.control == "pose" else "test_actions"
    rgb, ctrl, n = d["test_rgb"], d[key], len(d["test_rgb"])
    g = torch.Generator().manual_seed(0)
    short = [
        float((sample_chunk(model, ctrl[i, j : j + T][None], rgb[i, j][None], 16, g)[0, 1:] - rgb[i, j + 1 : j + T]).abs().mean())
        for i, j in itertools.product(range(n), STARTS)
    ]
    long = []
    for i in range(n):
        cur, out = rgb[i, 0], []
        for k in range(80 // (T - 1)):
            clip = sample_chunk(model, ctrl[i, k * (T - 1) : k * (T - 1) + T][None], cur[None], 16, g)[0]
            out.append(clip[1:])
            cur = clip[-1]
        long.append(float((torch.cat(out) - rgb[i, 1:]).abs().mean()))
    r = {"short": np.mean(short), "long": np.mean(long)}
    if model.config.control == "pose":
        to_b, to_a = [], []
        for a, b in itertools.permutations(range(n), 2):
            for j in (0, 40):
                clip = sample_chunk(model, ctrl[b, j : j + T][None], rgb[a, j][None], 16, g)[0, 1:]
                sil = (torch.sigmoid(seg(clip)) > 0.5).float()
                to_b.append(iou(sil, bodies(d["test_pose"][b, j + 1 : j + T])))
                to_a.append(iou(sil, bodies(d["test_pose"][a, j + 1 : j + T])))
        r |= {"iou_b": np.mean(to_b), "iou_a": np.mean(to_a)}
    return r


def main() -> None:
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from bench_observation import make_corpus

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", default="1000,3000")
    ap.add_argument("--jitter", default="0,0.5")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--corpus", type=Path, default=None, help="a corpus made (and scanned) as this benchmark makes it")
    a = ap.parse_args()
    print(preamble("Observation model: pose control against the baseline; does it follow a swapped pose?"))
    with tempfile.TemporaryDirectory(prefix="bench_follow_") as tmp:
        corpus = a.corpus
        if corpus is None:
            corpus = make_corpus(Path(tmp), scan=True)
        d = load(corpus, a.device)
        shutil.rmtree(tmp, ignore_errors=True)
    seg = segmenter(d, a.device)
    with torch.no_grad():
        rec = (torch.sigmoid(seg(d["test_rgb"].flatten(0, 1))) > 0.5).float()
        truth = bodies(d["test_pose"]).flatten(0, 1)
    ceiling, chance = iou(rec, truth), iou(rec, truth.roll(81, 0))
    copy_short = np.mean([float((d["test_rgb"][i, j][None] - d["test_rgb"][i, j + 1 : j + T]).abs().mean())
                          for i in range(len(d["test_rgb"])) for j in STARTS])  # fmt: skip
    copy_long = np.mean([float((d["test_rgb"][i, :1] - d["test_rgb"][i, 1:]).abs().mean()) for i in range(len(d["test_rgb"]))])
    rows = []
    for steps in (int(x) for x in a.steps.split(",")):
        runs = [("pose", float(j)) for j in a.jitter.split(",")] + [("actions", 0.0)]
        for control, jitter in runs:
            t0 = time.perf_counter()
            model = train(d, control, steps, jitter, a.device)
            took = time.perf_counter() - t0
            r = evaluate(model, d, seg)
            iou_b, iou_a = (f"{r['iou_b']:.3f}", f"{r['iou_a']:.3f}") if "iou_b" in r else ("–", "–")
            rows.append([control, jitter, steps, f"{took:.0f}", f"{r['short']:.4f}", f"{r['long']:.4f}", iou_b, iou_a])
            print(f"  {rows[-1]}", flush=True)
    print(f"\n{len(d['train_rgb'])} train / {len(d['test_rgb'])} held-out chunks on {a.device}; copying the first frame: short "
          f"{copy_short:.4f}, long {copy_long:.4f}; segmenter IoU on recorded held-out frames {ceiling:.3f} "
          f"(against other chunks' masks {chance:.3f})\n")  # fmt: skip
    print(table(["control", "jitter", "steps", "train s", "short |Δ|", "long |Δ| (81 frames)", "IoU vs B (followed)", "IoU vs A (first frame)"], rows))


if __name__ == "__main__":
    main()
