"""Checkpoints: safetensors for every tensor, JSON for everything else, nothing pickled.

A checkpoint is a directory ``<out>/step-<NNNNNNNN>/`` holding

- ``model.safetensors``: the model's ``state_dict`` (tensor names as torch gives them);
- ``optimizer.safetensors``: the optimizer's per-parameter state, each tensor named
  ``state.<param index>.<key>`` (AdamW: ``step``, ``exp_avg``, ``exp_avg_sq``), plus the torch RNG state
  as ``rng.torch`` (uint8);
- ``meta.json``: the step, the model config, the optimizer's ``param_groups`` (hyper-parameters and
  parameter indices), the scheduler's state (plain numbers), and whatever the trainer adds (the
  normaliser, the data seed, the loss history, ...).

The directory is written under a temporary name and renamed into place, so a crash never leaves a
half-written checkpoint, and ``<out>/latest`` (a one-line text file, replaced atomically) names the
newest complete one. Loading reads tensors through safetensors only (no pickle, no code) and checks
that every optimizer tensor belongs to a parameter of the model.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import save_file

from marionette.io import read_json, read_tensors, write_bytes

CHECKPOINT_VERSION = 1
STEP_DIR = re.compile(r"step-\d{8}")


def _json_safe(v: Any) -> Any:
    if isinstance(v, torch.Tensor):
        return v.item() if v.numel() == 1 else v.tolist()
    if isinstance(v, dict):
        return {str(k): _json_safe(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_json_safe(x) for x in v]
    return v


def save_checkpoint(
    out: Path,
    step: int,
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer | None = None,
    scheduler: Any = None,
    meta: dict | None = None,
) -> Path:
    """Write ``<out>/step-<step>/`` atomically and point ``<out>/latest`` at it; returns its path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    final = out / f"step-{step:08d}"
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", dir=out))
    try:
        weights = {k: v.detach().contiguous().cpu() for k, v in model.state_dict().items()}
        save_file(weights, str(tmp / "model.safetensors"))
        info: dict[str, Any] = {"version": CHECKPOINT_VERSION, "step": int(step), **(meta or {})}
        tensors: dict[str, torch.Tensor] = {"rng.torch": torch.get_rng_state()}
        if optimizer is not None:
            sd = optimizer.state_dict()
            for idx, st in sd["state"].items():
                for key, val in st.items():
                    t = val if isinstance(val, torch.Tensor) else torch.tensor(val)
                    tensors[f"state.{idx}.{key}"] = t.detach().contiguous().cpu()
            info["optimizer"] = {"param_groups": _json_safe(sd["param_groups"])}
        if scheduler is not None:
            info["scheduler"] = _json_safe(scheduler.state_dict())
        save_file(tensors, str(tmp / "optimizer.safetensors"))
        (tmp / "meta.json").write_text(json.dumps(info, indent=1, sort_keys=True))
        for f in tmp.iterdir():
            with open(f, "rb") as fh:
                os.fsync(fh.fileno())
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    write_bytes(out / "latest", f"{final.name}\n".encode())
    return final


def latest_checkpoint(out: Path) -> Path | None:
    """The newest complete checkpoint under ``out`` (from ``latest``), or None."""
    p = Path(out) / "latest"
    if not p.exists():
        return None
    if p.stat().st_size > 64:
        raise ValueError(f"{p}: {p.stat().st_size} bytes, not a one-line checkpoint name")
    name = p.read_text(errors="replace").strip()
    d = Path(out) / name
    if not STEP_DIR.fullmatch(name) or d.is_symlink() or not (d / "meta.json").is_file():
        raise ValueError(f"{p}: names {name!r}, which is not a complete checkpoint step-NNNNNNNN in {out}")
    return d


def read_meta(ckpt: Path) -> dict:
    """A checkpoint's meta.json."""
    d = read_json(Path(ckpt) / "meta.json")
    version = d.get("version") if isinstance(d, dict) else None
    if version != CHECKPOINT_VERSION:
        raise ValueError(f"{ckpt}: checkpoint version {version!r}, this reader knows {CHECKPOINT_VERSION}")
    return d


def load_checkpoint(
    ckpt: Path,
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer | None = None,
    scheduler: Any = None,
    restore_rng: bool = True,
) -> dict:
    """Load weights (and optimizer, scheduler and RNG state) into the given objects; returns meta.json."""
    ckpt = Path(ckpt)
    meta = read_meta(ckpt)
    weights = read_tensors(ckpt / "model.safetensors")
    missing, unexpected = model.load_state_dict(weights, strict=False)
    if missing or unexpected:
        raise ValueError(f"{ckpt}: weights do not fit the model (missing {missing[:3]}, unexpected {unexpected[:3]})")
    tensors = read_tensors(ckpt / "optimizer.safetensors")
    if optimizer is not None:
        if "optimizer" not in meta:
            raise ValueError(f"{ckpt}: holds no optimizer state")
        n_params = sum(len(g["params"]) for g in optimizer.param_groups)
        state: dict[int, dict[str, torch.Tensor]] = {}
        for name, t in tensors.items():
            if not name.startswith("state."):
                continue
            _, idx, key = name.split(".", 2)
            if not 0 <= int(idx) < n_params:
                raise ValueError(f"{ckpt}: optimizer state for parameter {idx}, the model has {n_params}")
            state.setdefault(int(idx), {})[key] = t
        optimizer.load_state_dict({"state": state, "param_groups": meta["optimizer"]["param_groups"]})
    if scheduler is not None and "scheduler" in meta:
        scheduler.load_state_dict(meta["scheduler"])
    if restore_rng and "rng.torch" in tensors:
        torch.set_rng_state(tensors["rng.torch"])
    return meta
