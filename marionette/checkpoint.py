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

A model sharded by FSDP (parameters and optimizer state as DTensor shards) is saved in the same format,
whole: every rank takes part in ``full_state`` (each tensor's shards are gathered from all of them) and
rank 0 alone passes the result to ``write_checkpoint``. Loading into such a model, every rank reads the
whole checkpoint and keeps its own shard of each tensor (``shard_like``).
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import save_file
from torch import Tensor

from marionette.io import atomic_dir, read_bounded, read_json, read_tensors, regular_file, write_bytes

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


def is_dtensor(t: Any) -> bool:
    """Whether ``t`` is a DTensor (an FSDP shard). Asked without importing ``torch.distributed.tensor``, which
    takes a second or two: before something imported it, no DTensor exists."""
    module = sys.modules.get("torch.distributed.tensor")
    return module is not None and isinstance(t, module.DTensor)


def full_tensor(t: Tensor) -> Tensor:
    """``t`` whole, detached, on the CPU: a DTensor's shards gathered from every rank (collective: each rank
    calls it for the same tensors in the same order), any other tensor as it is."""
    if is_dtensor(t):
        t = t.detach().full_tensor()
    return t.detach().contiguous().cpu()


def full_state(
    model: torch.nn.Module, optimizer: torch.optim.Optimizer | None = None, keep: bool = True
) -> tuple[dict[str, Tensor], dict | None]:
    """What a checkpoint holds of ``model`` and ``optimizer``: the model's ``state_dict`` and the optimizer's
    (``{"state": {param index: {key: value}}, "param_groups": ...}``) with every tensor whole on the CPU
    (``full_tensor``). Under FSDP every rank calls it; the ranks that do not write pass ``keep`` False and hold
    one gathered tensor at a time (they get empty dicts)."""
    weights = {}
    for name, value in model.state_dict().items():
        whole = full_tensor(value)
        if keep:
            weights[name] = whole
    if optimizer is None:
        return weights, None
    sd = optimizer.state_dict()
    state: dict[int, dict[str, Any]] = {}
    for idx, st in sd["state"].items():
        for key, val in st.items():
            whole = full_tensor(val if isinstance(val, Tensor) else torch.tensor(val))
            if keep:
                state.setdefault(idx, {})[key] = whole
    return weights, {"state": state, "param_groups": sd["param_groups"] if keep else []}


def save_checkpoint(
    out: Path,
    step: int,
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer | None = None,
    scheduler: Any = None,
    meta: dict | None = None,
) -> Path:
    """Write ``<out>/step-<step>/`` atomically and point ``<out>/latest`` at it; returns its path. A model
    sharded over several ranks: ``full_state`` on every rank, then ``write_checkpoint`` on one."""
    weights, optimizer_state = full_state(model, optimizer)
    return write_checkpoint(out, step, weights, optimizer_state, scheduler, meta)


def write_checkpoint(
    out: Path,
    step: int,
    weights: dict[str, Tensor],
    optimizer_state: dict | None = None,
    scheduler: Any = None,
    meta: dict | None = None,
) -> Path:
    """``save_checkpoint`` of the state ``full_state`` took: ``weights`` (whole CPU tensors) and the optimizer's
    state dict (its tensors whole too), or None without an optimizer."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    final = out / f"step-{step:08d}"
    with atomic_dir(final) as tmp:
        save_file(weights, str(tmp / "model.safetensors"))
        info: dict[str, Any] = {"version": CHECKPOINT_VERSION, "step": int(step), **(meta or {})}
        tensors: dict[str, Tensor] = {"rng.torch": torch.get_rng_state()}
        if optimizer_state is not None:
            for idx, st in optimizer_state["state"].items():
                for key, val in st.items():
                    tensors[f"state.{idx}.{key}"] = val
            info["optimizer"] = {"param_groups": _json_safe(optimizer_state["param_groups"])}
        if scheduler is not None:
            info["scheduler"] = _json_safe(scheduler.state_dict())
        save_file(tensors, str(tmp / "optimizer.safetensors"))
        (tmp / "meta.json").write_text(json.dumps(info, indent=1, sort_keys=True))
    write_bytes(out / "latest", f"{final.name}\n".encode())
    return final


def latest_checkpoint(out: Path) -> Path | None:
    """The newest complete checkpoint under ``out`` (from ``latest``), or None."""
    p = Path(out) / "latest"
    if not p.exists():
        return None
    name = read_bounded(p, 64, "a one-line checkpoint name").decode(errors="replace").strip()
    d = Path(out) / name
    if STEP_DIR.fullmatch(name) and not d.is_symlink() and (d / "meta.json").exists():
        regular_file(d / "meta.json")  # a FIFO or a device is named as such
        return d
    raise ValueError(f"{p}: names {name!r}, which is not a complete checkpoint step-NNNNNNNN in {out}")


def read_meta(ckpt: Path) -> dict:
    """A checkpoint's meta.json."""
    d = read_json(Path(ckpt) / "meta.json")
    version = d.get("version") if isinstance(d, dict) else None
    if version != CHECKPOINT_VERSION:
        raise ValueError(f"{ckpt}: checkpoint version {version!r}, this reader knows {CHECKPOINT_VERSION}")
    return d


def read_config(ckpt: Path, meta: dict, key: str, cls: type) -> Any:
    """``cls.from_json(meta[key])``: a checkpoint's saved model config, checked (sizes within their bounds, the memory
    the model would take within the machine's) before anything is allocated; every error names the checkpoint."""
    if not isinstance(meta.get(key), dict):
        raise ValueError(f"{Path(ckpt) / 'meta.json'}: no {key} object")
    try:
        return cls.from_json(meta[key])
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{Path(ckpt) / 'meta.json'}: {exc}") from None


def shard_like(whole: Tensor, like: Tensor) -> Tensor:
    """``whole`` laid out as ``like``: this rank's shard of it where ``like`` is a DTensor (FSDP; cut locally,
    as every rank read the same ``whole``), else ``whole`` itself."""
    if is_dtensor(like):
        from torch.distributed.tensor import distribute_tensor

        return distribute_tensor(whole, like.device_mesh, like.placements, src_data_rank=None)
    return whole


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
    own = model.state_dict()
    weights = {k: shard_like(v, own[k]) if k in own and v.shape == own[k].shape else v for k, v in weights.items()}
    missing, unexpected = model.load_state_dict(weights, strict=False)
    if missing or unexpected:
        raise ValueError(f"{ckpt}: weights do not fit the model (missing {missing[:3]}, unexpected {unexpected[:3]})")
    tensors = read_tensors(ckpt / "optimizer.safetensors")
    if optimizer is not None:
        if "optimizer" not in meta:
            raise ValueError(f"{ckpt}: holds no optimizer state")
        params = [p for g in optimizer.param_groups for p in g["params"]]
        state: dict[int, dict[str, Tensor]] = {}
        for name, t in tensors.items():
            if not name.startswith("state."):
                continue
            _, idx, key = name.split(".", 2)
            if not 0 <= int(idx) < len(params):
                raise ValueError(f"{ckpt}: optimizer state for parameter {idx}, the model has {len(params)}")
            param = params[int(idx)]  # a state tensor shaped like its parameter is sharded like it
            state.setdefault(int(idx), {})[key] = shard_like(t, param) if t.shape == param.shape else t
        optimizer.load_state_dict({"state": state, "param_groups": meta["optimizer"]["param_groups"]})
    if scheduler is not None and "scheduler" in meta:
        scheduler.load_state_dict(meta["scheduler"])
    if restore_rng and "rng.torch" in tensors:
        torch.set_rng_state(tensors["rng.torch"])
    return meta
