"""The knobs of a terrain scan and their checks, importable without the scan's heavy dependencies (the CLI's
parser reads them; ``terrain_scan.options.ScanOptions`` holds them)."""

from __future__ import annotations

import math

# the knobs of a scan, each with its check (what a value must be) and what it does; ``ScanOptions`` holds them
KNOBS: dict[str, tuple[str, str]] = {
    "frame_stride": ("an int ≥ 1", "use every Nth depth frame"),
    "depth_subsample": ("an int ≥ 1", "use every Nth depth pixel of every Nth row"),
    "voxel_m": ("a number > 0", "voxel size of the point down-sampling, metres"),
    "max_depth_m": ("a number > 0", "depth pixels beyond this are dropped (one code spans more metres far away)"),
    "min_normal_y": ("a number in [0, 1]", "a pooled point is ground when its normal's up component is at least this"),
    "image_normal_y": ("a number in [0, 1]", "a pixel is dropped when its normal in the image has a smaller up component"),
    "edge_rel": ("a number > 0", "a pixel next to a depth jump of more than this share of its depth is dropped"),
    "edge_m": ("a number in (0, 0.5)", "a layer whose points all lie this near its cell's edges may be a leak"),
    "smooth_radius": ("an int ≥ 0", "window radius of the 8-bit code smoothing (0: none)"),
    "smooth_tol": ("a number ≥ 0", "codes further than this from the centre's are left out of its smoothing"),
    "normal_radius_voxels": ("a number > 0", "normal estimation radius, in voxels"),
    "mask_radius_scale": ("a number ≥ 0", "characters are masked within this × the rig's capsule radius of a bone ..."),
    "mask_margin_m": ("a number ≥ 0", "... plus this many metres"),
    "contact_speed": ("a number > 0", "a contact joint at rest moves slower than this, m/s ..."),
    "contact_window": ("an int ≥ 0", "... over ± this many frames ..."),
    "contact_tol_m": ("a number ≥ 0", "... and lies within this of the entity's lowest joint"),
    "contact_hits": ("an int ≥ 0", "hits a ground contact adds (0: contacts off)"),
    "alias_fraction": ("a number in [0, 1]", "edge-alias rule by hits: a layer under this share of its cell's strongest ..."),
    "alias_dominance": ("a number ≥ 1", "... that a neighbour holds at its height this many times over ..."),
    "alias_support": ("an int ≥ 0", "... is an alias while it has fewer hits than this (0: the rule by hits off)"),
    "max_contact_gap_m": (
        "a number > 0",
        "a recording whose scanned ground stands further than this (m) from where its characters' feet stood is not "
        "added to the terrain: the depth mapping does not fit it (marionette calibrate-depth)",
    ),
}
DERIVE_KNOBS = ("alias_fraction", "alias_dominance", "alias_support")  # the stage's rebuild reads them, not a recording's scan
CHECK_KNOBS = ("max_contact_gap_m",)  # a check of a recording's scan: it changes whether a scan is used, not its bytes


def knob_ok(check: str, v) -> bool:
    """Whether ``v`` satisfies a ``KNOBS`` check."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        return False
    if check.startswith("an int") and not isinstance(v, int):
        return False
    if not math.isfinite(v):
        return False
    if check.endswith("≥ 1"):
        return v >= 1
    if check.endswith("≥ 0"):
        return v >= 0
    if check.endswith("> 0"):
        return v > 0
    if check.endswith("[0, 1]"):
        return 0 <= v <= 1
    if check.endswith("(0, 0.5)"):
        return 0 < v < 0.5
    raise AssertionError(check)
