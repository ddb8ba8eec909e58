"""The standard FVD feature extractor: Inception-I3D (Kinetics-400) loaded from a local safetensors file.

Network: Inception-v1 inflated to 3-D (Carreira & Zisserman 2017) as the widely used PyTorch port lays it
out, so a state dict converted from that port (``torch.load(..., weights_only=True)`` once, offline, then
``safetensors.torch.save_file``) loads strictly by name and shape:

    Conv3d_1a_7x7 (64, stride 2) → MaxPool3d_2a_3x3 (1×3×3, stride 1×2×2) → Conv3d_2b_1x1 (64) → Conv3d_2c_3x3 (192)
    → MaxPool3d_3a_3x3 (1×3×3, stride 1×2×2) → Mixed_3b, Mixed_3c → MaxPool3d_4a_3x3 (3×3×3, stride 2)
    → Mixed_4b … Mixed_4f → MaxPool3d_5a_2x2 (2×2×2, stride 2) → Mixed_5b, Mixed_5c
    → AvgPool3d (2×7×7, stride 1) → logits (1×1×1 convolution with bias, 400 classes)

Each unit is convolution (no bias) → BatchNorm3d (eps 1e-3) → ReLU with TensorFlow's "SAME" padding
(pad k − stride, or k − (size mod stride), split front ≤ back); pools pad the same way with zeros (their
inputs are ReLU outputs). An Inception module concatenates a 1×1×1 branch, 1×1×1 → 3×3×3, 1×1×1 → 3×3×3,
and a 3×3×3 max pool (stride 1) → 1×1×1.

Features, as FVD takes them: clips resized to 224 × 224 (bilinear), values in [−1, 1], at least 9
frames; the logits averaged over the remaining time steps → (N, 400).

Checked here: the module's parameter names and shapes (a file that does not match is refused, naming
the parameters). Not checked here (no reference weights can be fetched): numerical agreement with the
TF-Hub original that the published FVD numbers use.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from marionette.eval.features import check_videos

# per Inception module: input channels, [1×1, 3×3 reduce, 3×3, 3×3 reduce, 3×3, pool projection]
MIXED = {
    "Mixed_3b": (192, (64, 96, 128, 16, 32, 32)),
    "Mixed_3c": (256, (128, 128, 192, 32, 96, 64)),
    "Mixed_4b": (480, (192, 96, 208, 16, 48, 64)),
    "Mixed_4c": (512, (160, 112, 224, 24, 64, 64)),
    "Mixed_4d": (512, (128, 128, 256, 24, 64, 64)),
    "Mixed_4e": (512, (112, 144, 288, 32, 64, 64)),
    "Mixed_4f": (528, (256, 160, 320, 32, 128, 128)),
    "Mixed_5b": (832, (256, 160, 320, 32, 128, 128)),
    "Mixed_5c": (832, (384, 192, 384, 48, 128, 128)),
}
SIZE, MIN_FRAMES, CLASSES = 224, 9, 400


def same_pad(x: Tensor, kernel: tuple[int, int, int], stride: tuple[int, int, int]) -> Tensor:
    """Zero-pad (N, C, T, H, W) as TensorFlow's "SAME" does for this kernel and stride."""
    pads: list[int] = []
    for size, k, s in reversed(list(zip(x.shape[2:], kernel, stride))):
        p = max(k - s, 0) if size % s == 0 else max(k - size % s, 0)
        pads += [p // 2, p - p // 2]
    return F.pad(x, pads)


class Unit3D(nn.Module):
    def __init__(self, cin: int, cout: int, kernel: int = 1, stride: int = 1, bn: bool = True, relu: bool = True) -> None:
        super().__init__()
        self.kernel, self.stride, self.relu = (kernel,) * 3, (stride,) * 3, relu
        self.conv3d = nn.Conv3d(cin, cout, kernel, stride, bias=not bn)
        self.bn = nn.BatchNorm3d(cout, eps=1e-3, momentum=0.01) if bn else None

    def forward(self, x: Tensor) -> Tensor:
        x = self.conv3d(same_pad(x, self.kernel, self.stride))
        x = self.bn(x) if self.bn is not None else x
        return F.relu(x) if self.relu else x


class MaxPoolSame(nn.Module):
    def __init__(self, kernel: tuple[int, int, int], stride: tuple[int, int, int]) -> None:
        super().__init__()
        self.kernel, self.stride = kernel, stride

    def forward(self, x: Tensor) -> Tensor:
        return F.max_pool3d(same_pad(x, self.kernel, self.stride), self.kernel, self.stride)


class Inception(nn.Module):
    def __init__(self, cin: int, c: tuple[int, int, int, int, int, int]) -> None:
        super().__init__()
        self.b0 = Unit3D(cin, c[0])
        self.b1a, self.b1b = Unit3D(cin, c[1]), Unit3D(c[1], c[2], 3)
        self.b2a, self.b2b = Unit3D(cin, c[3]), Unit3D(c[3], c[4], 3)
        self.b3a, self.b3b = MaxPoolSame((3, 3, 3), (1, 1, 1)), Unit3D(cin, c[5])

    def forward(self, x: Tensor) -> Tensor:
        return torch.cat([self.b0(x), self.b1b(self.b1a(x)), self.b2b(self.b2a(x)), self.b3b(self.b3a(x))], dim=1)


class InceptionI3d(nn.Module):
    """Inception-I3D up to its Kinetics logits (module doc); ``forward`` → (N, classes, T')."""

    def __init__(self, classes: int = CLASSES) -> None:
        super().__init__()
        self.Conv3d_1a_7x7 = Unit3D(3, 64, 7, 2)
        self.MaxPool3d_2a_3x3 = MaxPoolSame((1, 3, 3), (1, 2, 2))
        self.Conv3d_2b_1x1 = Unit3D(64, 64)
        self.Conv3d_2c_3x3 = Unit3D(64, 192, 3)
        self.MaxPool3d_3a_3x3 = MaxPoolSame((1, 3, 3), (1, 2, 2))
        self.Mixed_3b, self.Mixed_3c = (Inception(*MIXED[k]) for k in ("Mixed_3b", "Mixed_3c"))
        self.MaxPool3d_4a_3x3 = MaxPoolSame((3, 3, 3), (2, 2, 2))
        for k in ("Mixed_4b", "Mixed_4c", "Mixed_4d", "Mixed_4e", "Mixed_4f"):
            setattr(self, k, Inception(*MIXED[k]))
        self.MaxPool3d_5a_2x2 = MaxPoolSame((2, 2, 2), (2, 2, 2))
        self.Mixed_5b, self.Mixed_5c = (Inception(*MIXED[k]) for k in ("Mixed_5b", "Mixed_5c"))
        self.logits = Unit3D(1024, classes, bn=False, relu=False)

    def forward(self, x: Tensor) -> Tensor:
        for name, module in self.named_children():
            if name == "logits":
                break
            x = module(x)
        return self.logits(F.avg_pool3d(x, (2, 7, 7), stride=1)).flatten(3).mean(-1)


class I3DExtractor:
    """FVD's features: the mean over time of Inception-I3D's Kinetics logits (module doc)."""

    is_fvd = True

    def __init__(self, network: InceptionI3d, name: str = "i3d", batch: int = 4) -> None:
        self.network, self.name, self.batch = network.eval().requires_grad_(False), name, int(batch)

    @classmethod
    def from_safetensors(cls, path: Path | str, batch: int = 4) -> I3DExtractor:
        """Load the network from a safetensors state dict, strictly; a ValueError names what does not fit."""
        from safetensors.torch import load_file

        path = Path(path)
        try:
            weights = load_file(str(path))
        except Exception as err:  # safetensors raises its own error types for a file that is not safetensors
            raise ValueError(f"{path}: not a safetensors file: {err}") from err
        net = InceptionI3d(classes=int(weights["logits.conv3d.bias"].shape[0]) if "logits.conv3d.bias" in weights else CLASSES)
        want = {k: tuple(v.shape) for k, v in net.state_dict().items()}
        missing = sorted(set(want) - set(weights))
        extra = sorted(set(weights) - set(want))
        wrong = sorted(k for k in set(want) & set(weights) if tuple(weights[k].shape) != want[k])
        if missing or extra or wrong:
            show = lambda ks: ", ".join(ks[:6]) + (f" (+{len(ks) - 6})" if len(ks) > 6 else "")  # noqa: E731
            raise ValueError(
                f"{path}: not an Inception-I3D state dict: missing [{show(missing)}], unexpected [{show(extra)}], "
                f"other shapes [{show(wrong)}]"
            )
        net.load_state_dict(weights)
        return cls(net, name=f"i3d({path.name})", batch=batch)

    @torch.inference_mode()
    def extract(self, videos: Tensor) -> np.ndarray:
        """(N, T, 3, H, W) in [−1, 1], T ≥ 9 → (N, classes) float64."""
        v = check_videos(videos, "videos")
        if v.shape[1] < MIN_FRAMES:
            raise ValueError(f"videos of {v.shape[1]} frames: I3D needs at least {MIN_FRAMES}")
        out = []
        for clips in v.split(self.batch):
            N, T = clips.shape[:2]
            x = F.interpolate(clips.flatten(0, 1), size=(SIZE, SIZE), mode="bilinear", align_corners=False)
            x = x.view(N, T, 3, SIZE, SIZE).transpose(1, 2)  # (N, 3, T, 224, 224)
            out.append(self.network(x).mean(-1).double().numpy())  # logits (N, classes, T') averaged over time
        return np.concatenate(out)
