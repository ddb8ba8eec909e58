"""The dynamics models' split of the state vector, from the scene layout: the root stream (``E.root`` then
``E.rot6d`` of every articulated entity, layout order) and the body state (every articulated entity's root-local
``E.joints``, then every attachment's ``points``, in state order; the attachments' points are the body's tail)."""

from __future__ import annotations

from typing import Any

import numpy as np

from marionette.schema import Layout, SchemaError


def root_stream_slices(layout: Layout) -> list[tuple[str, slice]]:
    """The root stream's parts in order: per articulated entity (layout order) ``E.root`` then ``E.rot6d``."""
    return [(f"{e.name}.{part}", layout.slice(f"{e.name}.{part}")) for e in layout.articulated for part in ("root", "rot6d")]


def body_slices(layout: Layout) -> list[tuple[str, slice]]:
    """The body state's parts in state order: every articulated entity's ``joints``, every attachment's ``points``."""
    names = [f"{e.name}.joints" for e in layout.articulated] + [f"{e.name}.points" for e in layout.attachments]
    return sorted(((n, layout.slice(n)) for n in names), key=lambda part: part[1].start)


def _indices(parts: list[tuple[str, slice]]) -> list[int]:
    return [i for _, s in parts for i in range(s.start, s.stop)]


def root_index(layout: Layout) -> list[int]:
    """State indices of the root stream, in root-stream order."""
    return _indices(root_stream_slices(layout))


def body_index(layout: Layout) -> list[int]:
    """State indices of the body state, in body order."""
    return _indices(body_slices(layout))


def split_state(state: Any, layout: Layout) -> tuple[Any, Any]:
    """State (..., dim) → root stream (..., root_dim) and body state (..., body_dim); numpy or torch."""
    return state[..., root_index(layout)], state[..., body_index(layout)]


def join_state(root: Any, body: Any, layout: Layout) -> Any:
    """Root stream (..., root_dim) and body state (..., body_dim) → state (..., dim); numpy or torch."""
    if isinstance(root, np.ndarray):
        out = np.zeros((*root.shape[:-1], layout.dim), np.result_type(root, body))
    else:
        import torch  # a tensor came in, so torch is loaded; importing it here keeps this module torch-free

        out = root.new_zeros(*root.shape[:-1], layout.dim, dtype=torch.promote_types(root.dtype, body.dtype))
    out[..., root_index(layout)] = root
    out[..., body_index(layout)] = body
    return out


def weapon_range(layout: Layout) -> tuple[int, int]:
    """[start, stop) of the attachments' points within the body state (empty at the end when there are none)."""
    at, found = 0, []
    for name, s in body_slices(layout):
        width = s.stop - s.start
        if name.endswith(".points"):
            found.append((at, at + width))
        at += width
    if not found:
        return at, at
    if any(a[1] != b[0] for a, b in zip(found, found[1:])):
        raise SchemaError(f"layout {layout.scene!r}: the attachments' points are not contiguous in the body state")
    return found[0][0], found[-1][1]
