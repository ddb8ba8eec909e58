"""The bounds a model config read from outside (a checkpoint's or a model directory's JSON) must fall within, and the
memory its parameters would take, checked against the machine before anything is allocated."""

from __future__ import annotations

import os

MAX_LAYERS = 512
MAX_WIDTH = 16384  # a transformer's model width
MAX_HEADS = 1024
MAX_WINDOW = 1 << 16  # frames a dynamics model attends over
MAX_VOCAB = 1 << 20  # tokens of one entity's action vocabulary
MAX_PIXELS = 8192  # an observation model's frame height or width


def check_int(value: object, name: str, low: int, high: int, what: str) -> int:
    """``value`` if it is an int (not a bool) in [low, high]; a ValueError naming ``what`` and ``name`` otherwise."""
    if type(value) is not int or not low <= value <= high:
        raise ValueError(f"{what}: {name} {value!r} is not an integer in [{low}, {high}]")
    return value


def machine_memory() -> int:
    """Bytes of physical memory on this machine."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def transformer_parameters(layers: int, width: int, mlp_ratio: int) -> int:
    """Parameters of a stack of pre-norm transformer blocks: attention (4 width²) and the MLP (2 · ratio · width²)."""
    return layers * (4 + 2 * mlp_ratio) * width * width


def check_memory(parameters: int, what: str, limit: int | None = None) -> None:
    """A ValueError naming ``what`` when ``parameters`` float32 weights alone would take more than ``limit`` bytes
    (default: the machine's memory)."""
    need, have = 4 * parameters, machine_memory() if limit is None else limit
    if need > have:
        raise ValueError(
            f"{what}: about {parameters:,} parameters, {need / 2**30:,.1f} GiB of float32 weights, more than this "
            f"machine's {have / 2**30:,.1f} GiB"
        )
