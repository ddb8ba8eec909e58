"""The device check: one table of the bridge on a GPU's EGL driver, a dynamics step and a ``train wan`` step.

On a machine with one NVIDIA GPU, in under 8 minutes: the bridge at 704×1280 against llvmpipe, a dynamics training
step at the paper preset and a ``train wan`` step at a reduced size.

    bash benchmarks/device.sh [--dry] [--only bridge,dynamics,wan] [--peak-tflops T]

Each part runs in a process of its own (this script with ``--part``), one after the other so that no two share the
GPU while timed (under ``--dry`` side by side, one thread each: there the paths are checked, not the speed). A part
that fails or runs past its time limit shows ``failed`` in its rows, its error goes to stderr, and the script exits
1. Without ``--dry`` the script needs torch with CUDA and a visible GPU, and says which is missing (exit 2) before
running anything.

Bridge. One seeded synthetic recording made, ingested and scanned by ``bench_bridge.make_clip`` (not timed): the
first frames of its first segment, seen through the recorded camera at the bridge size, with the stage's scanned
terrain and ``RenderSettings()`` defaults. ``Rasterizer.render_planes`` draws every frame on the default EGL (on a
GPU machine the vendor's driver, when its glvnd vendor file is installed): frames/s is the median of the repeats
after one warm-up pass. The same frames are then drawn by Mesa's llvmpipe in a process whose EGL loader sees only
Mesa's vendor file (``__EGL_VENDOR_LIBRARY_FILENAMES``), on Mesa's software device (the last EGL device Mesa lists,
after any DRM device it finds: ``GLCONTEXT_DEVICE_INDEX``, which moderngl's EGL backend reads), its threads Mesa's
default, and its code planes compared with the first's: the share of pixels whose codes differ in any channel, the
largest code difference per channel (height R, id G, inverse depth B) over every pixel and over the pixels both
cover with the same id, and the pixels whose id differs (the id is meant to be exact). Under ``--dry`` both
renders are llvmpipe: the comparison checks the path, and llvmpipe against itself.

Dynamics. ``DynamicsModel`` at a preset (the paper's: ActionGPT 4 layers of width 256, PoseGPT 8 of 512, window
512) for the duel scene with the switches ``TrainConfig``'s defaults turn on, random inputs of the training batch's
shapes (window + 1 frames, terrain features and their known mask), and one optimizer step as ``train`` takes it:
``losses`` under bf16 autocast (on CUDA; float32 on the CPU), backward, gradient clipping, AdamW and its schedule
(``make_optimizer``). Tokens/s counts frames of the window per second, each read by both transformers. Model FLOPs
per token are 6 · N (N: both models' parameters less their embedding tables) plus, per transformer, 12 · layers ·
width · window for attention (PaLM's count: the causal mask not halved); MFU is model FLOP/s over the GPU's dense
bf16 peak, from ``PEAK_BF16_DENSE_TFLOPS`` by the GPU's name (or ``--peak-tflops``).

Wan. ``WanTransformer3DModel`` with Wan2.2-Fun-5B-Control's block (``bench_wan_train.FIVE_B``: width 3072, 24 heads,
FFN 14336) but fewer layers, random weights, wrapped in ``WanFunControl`` with a tiny VAE (its latent shape is all
the step reads) and made trainable by ``trainable_transformer`` (every weight, bf16 autocast, gradient
checkpointing); one step is ``flow_batch`` of random latents of one 81-frame window at 704×1280, ``flow_loss``,
backward, clipping at 1 and AdamW as ``train`` builds it. Seconds per step (median over the timed steps) and the
peak memory: ``torch.cuda.max_memory_allocated`` on a GPU, the process's peak RSS on the CPU.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import preamble, table, time_call  # noqa: E402

PARTS = ("bridge", "dynamics", "wan")
# NVIDIA's datasheets, dense (without sparsity); a GPU takes the first entry its name contains
PEAK_BF16_DENSE_TFLOPS = (
    ("H100 PCIe", 756.0),
    ("H100 NVL", 835.0),
    ("H100", 989.0),  # SXM
    ("H200 NVL", 835.0),
    ("H200", 989.0),
    ("A100", 312.0),
)
VOCAB = (7, 7)  # per entity: the synthetic game's six clips + "no valid action"
EGL_VENDOR_DIRS = ("/etc/glvnd/egl_vendor.d", "/usr/share/glvnd/egl_vendor.d", "/usr/local/share/glvnd/egl_vendor.d")
# each part's limit in seconds: together under the 8 minutes a device run is given
TIME_LIMIT_S = {"scene": 75, "render": 45, "render-mesa": 75, "dynamics": 90, "wan": 150}
HEADER = ["part", "measure", "value", "setting"]
FAILED = "failed"


@dataclass(frozen=True)
class Sizes:
    """What each part runs at."""

    bridge_hw: tuple[int, int]  # (height, width) of the render
    clip_seconds: float  # the synthetic recording's length
    clip_frames: int  # frames rendered (at most)
    repeats: int  # timed render passes
    dyn_preset: str  # dynamics.config.PRESETS
    dyn_window: int | None  # None: the preset's
    dyn_batch: int
    wan_dims: str  # bench_wan_train's FIVE_B (the 5B's block) or SMALL
    wan_layers: int
    wan_frames: int  # one window, 4k + 1
    wan_hw: tuple[int, int]
    warmup: int  # untimed training steps
    steps: int  # timed training steps


DEVICE = Sizes(
    bridge_hw=(704, 1280), clip_seconds=10.0, clip_frames=120, repeats=3,
    dyn_preset="paper", dyn_window=None, dyn_batch=16,  # TrainConfig's batch
    wan_dims="FIVE_B", wan_layers=6, wan_frames=81, wan_hw=(704, 1280),
    warmup=3, steps=10,
)  # fmt: skip
DRY = Sizes(
    bridge_hw=(36, 64), clip_seconds=2.0, clip_frames=8, repeats=1,  # 2 s: the shortest recording that ingests a segment
    dyn_preset="tiny", dyn_window=16, dyn_batch=2,
    wan_dims="SMALL", wan_layers=2, wan_frames=9, wan_hw=(64, 128),
    warmup=1, steps=2,
)  # fmt: skip


# -- the parts, each run in a process of its own ----------------------------------------------------------


def part_scene(sizes: Sizes, work: Path) -> dict:
    """Make the clip and save what a renderer needs (cameras, bone capsules, heights, settings, terrain)."""
    import numpy as np
    from bench_bridge import make_clip

    (work / "clip").mkdir()
    clip = make_clip(work / "clip", sizes.clip_seconds, sizes.clip_frames, seed=0)
    H, W = sizes.bridge_hw
    cams = clip.cameras(H, W)
    a, b, r, ids = (np.concatenate([frame[k] for frame in clip.bones]) for k in range(4))
    np.savez(
        work / "scene.npz",
        K=cams.K, pos=cams.pos, rot=cams.rot, valid=cams.valid, size=[W, H], h=clip.h,
        a=a, b=b, r=r, ids=ids, counts=[len(frame[0]) for frame in clip.bones],
        vertices=clip.terrain.vertices, faces=clip.terrain.faces,
    )  # fmt: skip
    (work / "settings.json").write_text(json.dumps(asdict(clip.settings)))
    return {"frames": len(clip), "triangles": len(clip.terrain.faces), "bones": sum(len(b[0]) for b in clip.bones) / len(clip)}


def read_scene(work: Path) -> tuple[dict, object, list]:
    """The scene ``part_scene`` saved: its arrays, the cameras and each frame's bone capsules."""
    import numpy as np

    from marionette.bridge.camera import Cameras

    with np.load(work / "scene.npz", allow_pickle=False) as z:
        scene = {k: z[k] for k in z.files}
    W, H = (int(v) for v in scene["size"])
    cams = Cameras(scene["K"], scene["pos"], scene["rot"], scene["valid"], W, H)
    ends = np.cumsum(scene["counts"])
    bones = [tuple(scene[k][e - n : e] for k in ("a", "b", "r", "ids")) for n, e in zip(scene["counts"], ends)]
    return scene, cams, bones


def egl_device_count() -> int:
    """The devices this process's EGL lists (``eglQueryDevicesEXT``)."""
    import ctypes
    import ctypes.util

    egl = ctypes.CDLL(ctypes.util.find_library("EGL"))
    egl.eglGetProcAddress.restype = ctypes.c_void_p
    egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
    address = egl.eglGetProcAddress(b"eglQueryDevicesEXT")
    if not address:
        raise RuntimeError("this EGL has no eglQueryDevicesEXT")
    query = ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_int, ctypes.c_void_p, ctypes.POINTER(ctypes.c_int))(address)
    count = ctypes.c_int(0)
    if not query(0, None, ctypes.byref(count)):
        raise RuntimeError("eglQueryDevicesEXT failed")
    return count.value


def part_render(sizes: Sizes, work: Path, mesa: bool) -> dict:
    """Render the scene on this process's EGL: frames/s, then its code planes written (the first renderer) or, on
    Mesa's software device (``mesa``), compared with the ones written."""
    import numpy as np

    from marionette.bridge.render import Rasterizer
    from marionette.bridge.targets import RenderSettings

    if mesa:  # the rasterizer opens the device GLCONTEXT_DEVICE_INDEX names; Mesa lists its software device last
        os.environ["GLCONTEXT_DEVICE_INDEX"] = str(egl_device_count() - 1)
    scene, cams, bones = read_scene(work)
    (h_min, h_max), s = scene["h"], RenderSettings(**json.loads((work / "settings.json").read_text()))
    H, W = sizes.bridge_hw
    codes_path = work / "codes.npy"
    with Rasterizer(W, H) as rast:
        info = rast.ctx.info
        rast.set_terrain(scene["vertices"], scene["faces"])

        def frames():
            for i in range(len(bones)):
                yield rast.render_planes(cams, i, bones[i], h_min, h_max, s.z_near, s.z_far, s.cull_m)

        seconds, _ = time_call(lambda: sum(1 for _ in frames()), sizes.repeats)
        out = {"renderer": info["GL_RENDERER"], "version": info["GL_VERSION"], "fps": len(bones) / seconds}
        if not mesa:
            codes = np.lib.format.open_memmap(codes_path, "w+", np.uint16, (len(bones), 3, H, W))
            for i, planes in enumerate(frames()):
                codes[i] = planes
            codes.flush()
            return out
        return {**out, **compare_codes(frames(), np.load(codes_path, mmap_mode="r"))}


def compare_codes(frames, reference) -> dict:
    """Pixels whose codes differ between ``frames`` and ``reference`` ((N, 3, H, W) planes in G, B, R order:
    id, inverse depth, height), and the largest difference per channel, over all pixels and over the pixels both
    cover with the same id."""
    import numpy as np

    differ = id_differ = pixels = 0
    most = np.zeros(3, np.int64)  # G, B, R
    most_agreeing = np.zeros(3, np.int64)
    for planes, ref in zip(frames, reference, strict=True):
        d = np.abs(planes.astype(np.int32) - ref.astype(np.int32))  # (3, H, W)
        pixels += d[0].size
        differ += int(np.count_nonzero(d.any(0)))
        id_differ += int(np.count_nonzero(d[0]))
        most = np.maximum(most, d.reshape(3, -1).max(1))
        same = (d[0] == 0) & planes.any(0) & ref.any(0)
        if same.any():
            most_agreeing = np.maximum(most_agreeing, d[:, same].max(1))
    return {
        "differ_pct": 100.0 * differ / pixels,
        "id_differ": id_differ,
        "max_id": int(most[0]),
        "max_depth": int(most[1]),
        "max_height": int(most[2]),
        "max_depth_same_id": int(most_agreeing[1]),
        "max_height_same_id": int(most_agreeing[2]),
        "pixels": pixels,
    }


def device_of_torch() -> tuple[object, str]:
    """The CUDA device where there is one, else the CPU; and a line naming it with torch's version."""
    import torch

    if torch.cuda.is_available():
        return torch.device("cuda"), f"{torch.cuda.get_device_name()}, torch {torch.__version__}, CUDA {torch.version.cuda}"
    return torch.device("cpu"), f"CPU, torch {torch.__version__}"


def peak_memory_gib(device) -> tuple[float, str]:
    """The allocator's peak on a GPU, the process's peak RSS on the CPU; and which of the two it is."""
    import torch

    if device.type == "cuda":
        return torch.cuda.max_memory_allocated() / 2**30, "torch.cuda.max_memory_allocated"
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, "peak RSS of the process (CPU)"  # KiB on Linux


def timed_steps(step, device, warmup: int, steps: int) -> list[float]:
    """Seconds of each of ``steps`` calls of ``step`` after ``warmup`` untimed ones, the device synchronised."""
    import torch

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize()

    for _ in range(warmup):
        step()
    sync()
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        step()
        sync()
        times.append(time.perf_counter() - t0)
    return times


def dynamics_config(train, layout):
    """The model ``train`` builds for a corpus of ``layout`` with ``VOCAB``: the preset's sizes and the config's
    switches; each token's class and clip length made up (they size nothing)."""
    from marionette.dynamics.config import N_TOKEN_CLASSES, DynamicsConfig

    classes = tuple(tuple(k % (N_TOKEN_CLASSES + 1) for k in range(v)) for v in VOCAB)
    lengths = tuple(tuple(0.0 if k == 0 else 30.0 for k in range(v)) for v in VOCAB)
    return DynamicsConfig.preset(
        train.preset,
        layout,
        VOCAB,
        **({} if train.window is None else {"window": train.window}),
        relative_position=train.relative,
        body_anchor=train.body_anchor,
        rotation_anchor=train.rotation_anchor,
        displacement_gate=train.displacement_gate,
        adaptive_copy=train.adaptive_copy,
        pose_progress=train.pose_progress,
        token_classes=classes if train.token_classes else (),
        events_end=lengths if train.events_end else (),
    )


def random_batch(dyn, batch: int, device):
    """A training batch of random inputs: ``batch`` windows of ``dyn.window`` + 1 frames."""
    import torch

    from marionette.dynamics.data import Batch
    from marionette.dynamics.model import Frames

    g = torch.Generator().manual_seed(0)
    B, T, N = batch, dyn.window + 1, dyn.n_entities
    frames = Frames(
        root=torch.randn(B, T, dyn.root_dim, generator=g),
        body=torch.randn(B, T, dyn.body_dim, generator=g),
        tokens=torch.stack([torch.randint(0, v, (B, T), generator=g) for v in dyn.vocab_sizes], dim=-1),
        progress=torch.rand(B, T, N, generator=g),
        terrain=torch.randn(B, T, N, dyn.terrain_features, generator=g),
        relative=torch.randn(B, T, N, 3, generator=g),
    )
    known = torch.rand(B, T, N, dyn.terrain_features, generator=g) < 0.9
    frames = Frames(**{k: v.to(device) for k, v in vars(frames).items() if v is not None})
    return Batch(frames, known.to(device), (), ())


def part_dynamics(sizes: Sizes) -> dict:
    """Optimizer steps of the dynamics model on random batches: tokens/s and model FLOP/s."""
    import numpy as np
    import torch
    from torch import nn

    from marionette import training
    from marionette.dynamics.config import TrainConfig
    from marionette.dynamics.model import DynamicsModel
    from marionette.dynamics.normalise import Normaliser
    from marionette.dynamics.train import PenetrationHinge, losses, make_optimizer
    from marionette.schema import load_scene

    device, device_line = device_of_torch()
    bf16 = device.type == "cuda"
    config = TrainConfig(preset=sizes.dyn_preset, window=sizes.dyn_window, batch_size=sizes.dyn_batch, bf16=bf16)
    layout = load_scene("duel")
    dyn = dynamics_config(config, layout)
    normaliser = Normaliser(
        np.zeros(dyn.root_dim), np.ones(dyn.root_dim), np.zeros(dyn.body_dim), np.ones(dyn.body_dim), 1e-3, layout.hash, "train"
    )
    model = DynamicsModel(dyn, seed=0).to(device)
    opt, sched = make_optimizer(model, config)
    hinge = PenetrationHinge(layout, normaliser, config.hinge_margin)
    batch = random_batch(dyn, config.batch_size, device)
    autocast = torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16)
    count = iter(range(1 << 30))
    model.train()

    def step() -> None:
        noise = training.noise_generator(config.seed, next(count), 0)
        with autocast:
            terms = losses(model, model.action, model.pose, batch, normaliser, config, hinge, noise)
        opt.zero_grad(set_to_none=True)
        terms["total"].backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
        opt.step()
        sched.step()

    seconds = statistics.median(timed_steps(step, device, sizes.warmup, sizes.steps))
    embeddings = sum(m.weight.numel() for m in model.modules() if isinstance(m, nn.Embedding))
    params = sum(p.numel() for p in model.parameters())
    attention = sum(12 * spec.layers * spec.width * dyn.window for spec in (dyn.action_gpt, dyn.pose_gpt))
    tokens = config.batch_size * dyn.window
    flops_per_token = 6 * (params - embeddings) + attention
    return {
        "device": device_line,
        "gpu": torch.cuda.get_device_name() if device.type == "cuda" else None,
        "params": params,
        "embeddings": embeddings,
        "window": dyn.window,
        "batch": config.batch_size,
        "bf16": bf16,
        "tokens_per_s": tokens / seconds,
        "tflops": flops_per_token * tokens / seconds / 1e12,
        "step_s": seconds,
    }


def part_wan(sizes: Sizes) -> dict:
    """Optimizer steps of a Wan-shaped transformer as ``train wan`` takes them: seconds per step and peak memory."""
    import torch
    from bench_wan_train import FIVE_B, SMALL
    from diffusers import AutoencoderKLWan, WanTransformer3DModel

    from marionette.observation.config import WanTrainConfig
    from marionette.observation.wan import WanFunControl
    from marionette.observation.wan_train import Trainable, flow_batch, flow_loss, trainable_transformer

    device, device_line = device_of_torch()
    dims = {**{"FIVE_B": FIVE_B, "SMALL": SMALL}[sizes.wan_dims], "num_layers": sizes.wan_layers}
    torch.manual_seed(0)
    tiny_vae = AutoencoderKLWan(
        base_dim=8, z_dim=dims["out_channels"], in_channels=12, out_channels=12, is_residual=True, patch_size=2,
        latents_mean=[0.0] * dims["out_channels"], latents_std=[1.0] * dims["out_channels"], dim_mult=[1, 1, 1, 1],
        num_res_blocks=1, scale_factor_spatial=16, scale_factor_temporal=4,
    )  # fmt: skip
    model = WanFunControl(WanTransformer3DModel(**dims), tiny_vae, frames=sizes.wan_frames)
    config = WanTrainConfig(
        backbone="(random weights)", frames=sizes.wan_frames, bf16=True, gradient_checkpointing=True, device=device.type
    )
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    transformer = trainable_transformer(model, config, device)
    trainable = Trainable(transformer)
    opt = torch.optim.AdamW(trainable.parameters(), lr=config.lr, betas=(0.9, 0.99), weight_decay=0.0)
    context, patch = model.context.float().to(device), tuple(model.transformer.config.patch_size)
    H, W = sizes.wan_hw
    latent = (model.vae.config.z_dim, (sizes.wan_frames - 1) // model.temporal + 1, H // model.spatial, W // model.spatial)
    g = torch.Generator().manual_seed(0)
    latents = [{k: torch.randn(latent, generator=g) for k in ("x0", "control", "masked")}]

    def step() -> None:
        inp, per_frame, target, _, _ = flow_batch(latents, [0] * config.batch_size, g, config.shift, model.temporal)
        loss = flow_loss(transformer, patch, context, inp, per_frame, target, config.bf16)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(trainable.parameters(), 1.0)
        opt.step()

    seconds = statistics.median(timed_steps(step, device, sizes.warmup, sizes.steps))
    tokens = latent[1] * (latent[2] // patch[1]) * (latent[3] // patch[2])
    peak, memory = peak_memory_gib(device)
    return {
        "device": device_line,
        "params": sum(p.numel() for p in trainable.parameters()),
        "step_s": seconds,
        "peak_gib": peak,
        "memory": memory,
        "tokens": tokens,
        "width": dims["num_attention_heads"] * dims["attention_head_dim"],
        "layers": dims["num_layers"],
    }


# -- the driver: parts in order, then the table ------------------------------------------------------------


def cuda_missing() -> str | None:
    """What keeps this Python from training on a GPU, in words; None when nothing does."""
    try:
        import torch
    except ImportError:
        return f"torch is not installed for {sys.executable}"
    if torch.version.cuda is None:
        return (
            f"torch {torch.__version__} is a build without CUDA (torch.version.cuda is None): install a CUDA build of "
            "torch in the venv (or point $PYTHON at a Python that has one), or run with --dry for the CPU check"
        )
    if not torch.cuda.is_available():
        return (
            f"torch {torch.__version__} (CUDA {torch.version.cuda}) sees no GPU: torch.cuda.is_available() is False "
            "(no NVIDIA driver, or CUDA_VISIBLE_DEVICES hides the GPU)"
        )
    return None


def egl_vendor_files() -> list[Path]:
    """The glvnd EGL vendor files installed (the drivers EGL may load), in the loader's search order."""
    return [p for d in EGL_VENDOR_DIRS for p in sorted(Path(d).glob("*.json"))]


def mesa_env() -> dict[str, str]:
    """The environment of a process whose EGL loads Mesa alone; KeyError naming the directories searched when
    Mesa's vendor file is not installed."""
    mesa = [p for p in egl_vendor_files() if "mesa" in p.name]
    if not mesa:
        raise KeyError(f"no Mesa EGL vendor file (*mesa*.json) in {', '.join(EGL_VENDOR_DIRS)}")
    env = {k: v for k, v in os.environ.items() if k != "LP_NUM_THREADS"}
    return {**env, "__EGL_VENDOR_LIBRARY_FILENAMES": str(mesa[0])}


def run_part(name: str, args: list[str], dry: bool, work: Path, limit: str, env: dict[str, str] | None = None) -> dict | None:
    """Run ``--part name`` in a fresh process; its result, or None (its error on stderr) when it failed."""
    out = work / f"{limit}.json"
    command = [sys.executable, str(Path(__file__).resolve()), "--part", name, "--work", str(work), "--out", str(out), *args]
    command += ["--dry"] if dry else []
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=TIME_LIMIT_S[limit], env=env)
    except subprocess.TimeoutExpired:
        print(f"{limit}: ran past its limit of {TIME_LIMIT_S[limit]} s", file=sys.stderr)
        return None
    if done.returncode != 0 or not out.exists():
        tail = "\n".join((done.stdout + done.stderr).strip().splitlines()[-20:])
        print(f"{limit}: exit {done.returncode}\n{tail}\n", file=sys.stderr)
        return None
    return json.loads(out.read_text())


def peak_tflops(gpu: str | None, given: float | None) -> tuple[float | None, str]:
    """The dense bf16 peak to measure MFU against, and where it came from."""
    if given is not None:
        return given, "given (--peak-tflops)"
    if gpu is None:
        return None, "no peak for a CPU"
    for name, tflops in PEAK_BF16_DENSE_TFLOPS:
        if name in gpu:
            return tflops, f"{name} datasheet, dense, from the GPU's name {gpu!r}"
    return None, f"{gpu!r} is not in PEAK_BF16_DENSE_TFLOPS: give --peak-tflops"


def bridge_rows(sizes: Sizes, dry: bool, scene: dict | None, first: dict | None, mesa: dict | None) -> list[list[str]]:
    H, W = sizes.bridge_hw
    clip = (
        f"{scene['frames']} frames, {scene['bones']:.0f} bones a frame, terrain {scene['triangles']} triangles"
        if scene
        else "no clip"
    )
    vendors = "EGL vendor files: " + (", ".join(p.name for p in egl_vendor_files()) or "none")
    if not dry and first is not None and "llvmpipe" in first["renderer"]:
        vendors += "; NOT the GPU: EGL found no vendor driver for it (NVIDIA's is 10_nvidia.json)"

    def get(result: dict | None, key: str, form: str = "{}") -> str:
        return FAILED if result is None else form.format(result[key])

    differ = "" if mesa is None else f"of {mesa['pixels']} pixels"
    same_id = "10-bit codes, pixels both cover with one id"
    return [
        ["bridge", "GL renderer, default EGL", get(first, "renderer"), vendors],
        ["bridge", "render frames/s, default EGL", get(first, "fps", "{:.1f}"), f"{H}×{W}, {clip}, median of {sizes.repeats}"],
        ["bridge", "GL renderer, Mesa forced", get(mesa, "renderer"), "EGL loads Mesa alone; its software device"],
        ["bridge", "render frames/s, Mesa forced", get(mesa, "fps", "{:.1f}"), f"{H}×{W}, Mesa's default threads"],
        ["bridge", "pixels whose codes differ (%)", get(mesa, "differ_pct", "{:.4f}"), f"any channel, {differ}"],
        ["bridge", "pixels whose id differs", get(mesa, "id_differ"), "the id is meant to be exact"],
        ["bridge", "max code difference, height (R)", get(mesa, "max_height"), "10-bit codes, every pixel"],
        ["bridge", "max code difference, id (G)", get(mesa, "max_id"), "10-bit codes, every pixel"],
        ["bridge", "max code difference, inverse depth (B)", get(mesa, "max_depth"), "10-bit codes, every pixel"],
        ["bridge", "max code difference, height (R), same id", get(mesa, "max_height_same_id"), same_id],
        ["bridge", "max code difference, inverse depth (B), same id", get(mesa, "max_depth_same_id"), same_id],
    ]


def dynamics_rows(sizes: Sizes, dyn: dict | None, given_peak: float | None) -> list[list[str]]:
    if dyn is None:
        measures = ("parameters", "tokens/s", "model TFLOP/s", "peak bf16 dense TFLOP/s", "MFU (%)")
        return [["dynamics", m, FAILED, ""] for m in measures]
    peak, source = peak_tflops(dyn["gpu"], given_peak)
    setting = f"preset {sizes.dyn_preset}, window {dyn['window']}, batch {dyn['batch']}, {'bf16 autocast' if dyn['bf16'] else 'float32'}"
    return [
        ["dynamics", "parameters", str(dyn["params"]), f"both models, {dyn['embeddings']} of them in embedding tables"],
        ["dynamics", "tokens/s", f"{dyn['tokens_per_s']:.0f}", f"{setting}, median of {sizes.steps} steps"],
        ["dynamics", "model TFLOP/s", f"{dyn['tflops']:.4g}", "6·N + attention 12·layers·width·window per token"],
        ["dynamics", "peak bf16 dense TFLOP/s", "—" if peak is None else f"{peak:g}", source],
        ["dynamics", "MFU (%)", "—" if peak is None else f"{100 * dyn['tflops'] / peak:.2f}", "model TFLOP/s over the peak"],
    ]


def wan_rows(sizes: Sizes, wan: dict | None) -> list[list[str]]:
    if wan is None:
        return [["wan", m, FAILED, ""] for m in ("trainable parameters", "s/step", "peak memory (GiB)")]
    H, W = sizes.wan_hw
    shape = (
        f"{wan['layers']} layers of width {wan['width']} ({sizes.wan_dims}), one {sizes.wan_frames}×{H}×{W} window "
        f"({wan['tokens']} tokens), full fine-tuning, bf16 autocast, gradient checkpointing"
    )
    return [
        ["wan", "trainable parameters", str(wan["params"]), shape],
        ["wan", "s/step", f"{wan['step_s']:.4g}", f"median of {sizes.steps} steps"],
        ["wan", "peak memory (GiB)", f"{wan['peak_gib']:.2f}", wan["memory"]],
    ]


def run_bridge(dry: bool, work: Path) -> tuple[dict | None, dict | None, dict | None]:
    """The clip, its render on the default EGL, and on Mesa's compared with it: each None where it failed."""
    scene = run_part("scene", [], dry, work, "scene")
    first = run_part("render", [], dry, work, "render") if scene is not None else None
    mesa = None
    if first is not None:
        try:
            mesa = run_part("render", ["--mesa"], dry, work, "render-mesa", env=mesa_env())
        except KeyError as err:
            print(f"render-mesa: {err.args[0]}", file=sys.stderr)
    return scene, first, mesa


def run_all(args: argparse.Namespace) -> int:
    """The parts in their own processes: one after the other on a GPU (none shares it while timed), side by side
    under ``--dry``, one thread each (the figures mean nothing there; the paths are what is checked). Prints the
    table; 1 if a part failed."""
    sizes = DRY if args.dry else DEVICE
    parts = set(args.only)
    env = {**os.environ, "OMP_NUM_THREADS": "1"} if args.dry else None
    with tempfile.TemporaryDirectory(prefix="bench_device_") as tmp, ThreadPoolExecutor(3 if args.dry else 1) as pool:
        work = Path(tmp)
        bridge = pool.submit(run_bridge, args.dry, work) if "bridge" in parts else None
        dyn = pool.submit(run_part, "dynamics", [], args.dry, work, "dynamics", env) if "dynamics" in parts else None
        wan = pool.submit(run_part, "wan", [], args.dry, work, "wan", env) if "wan" in parts else None
        rows = []
        rows += bridge_rows(sizes, args.dry, *bridge.result()) if bridge else []
        rows += dynamics_rows(sizes, dyn.result(), args.peak_tflops) if dyn else []
        rows += wan_rows(sizes, wan.result()) if wan else []
        ran = [f.result() for f in (dyn, wan) if f is not None and f.result() is not None]
    title = "Device check: the bridge on the GPU's EGL driver, a dynamics step, a `train wan` step"
    print(preamble(title + (" (--dry)" if args.dry else "")))
    print(f"torch: {ran[0]['device'] if ran else 'no torch part ran'}\n")
    print(table(HEADER, rows))
    return 1 if any(r[2] == FAILED for r in rows) else 0


def run_one(args: argparse.Namespace) -> None:
    sizes = DRY if args.dry else DEVICE
    work = Path(args.work)
    if args.part == "scene":
        result = part_scene(sizes, work)
    elif args.part == "render":
        result = part_render(sizes, work, args.mesa)
    elif args.part == "dynamics":
        result = part_dynamics(sizes)
    else:
        result = part_wan(sizes)
    Path(args.out).write_text(json.dumps(result))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dry", action="store_true", help="every part at tiny sizes on the CPU (well under a minute)")
    ap.add_argument("--only", type=lambda s: s.split(","), default=list(PARTS), help=f"some of {','.join(PARTS)}")
    ap.add_argument("--peak-tflops", type=float, help="the GPU's dense bf16 peak TFLOP/s, where its name is not in the table")
    ap.add_argument("--part", choices=("scene", "render", "dynamics", "wan"), help=argparse.SUPPRESS)
    ap.add_argument("--mesa", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--work", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.part:
        run_one(args)
        return
    unknown = set(args.only) - set(PARTS)
    if unknown:
        ap.error(f"--only: unknown parts {sorted(unknown)}; known: {', '.join(PARTS)}")
    if args.peak_tflops is not None and not (math.isfinite(args.peak_tflops) and args.peak_tflops > 0):
        ap.error("--peak-tflops must be a positive number")
    if not args.dry and (missing := cuda_missing()):
        print(f"benchmarks/device.sh: cannot run on this machine: {missing}.", file=sys.stderr)
        sys.exit(2)
    sys.exit(run_all(args))


if __name__ == "__main__":
    main()
