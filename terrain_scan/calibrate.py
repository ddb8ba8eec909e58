"""Calibrating the 8-bit depth mapping from a tree of recordings.

``calibrate_recordings`` reads every recording's (code, joint) pairs (``iter_pairs``) and fits the mapping to them
(``depth_fit.fit``); then, in a second pass, it reads the depth points on the cells where the characters stood
(``iter_contact_points``) and scales every depth so that the ground stands where their feet did
(``contact_scale.fit_contact_scale``). A recording that gives nothing gives its reason (``per_recording``).
``plot`` draws the pairs, the fits and the chosen mapping's residuals.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TypeVar

import numpy as np

from marionette.io import atomic_path
from marionette.recordings.errors import SampleError, SampleSkipped
from marionette.recordings.wildworld import SampleRef
from marionette.schema import Layout
from terrain_scan.contact_scale import ContactPoints, contact_points, fit_contact_scale
from terrain_scan.depth import CODES, DepthDecoder
from terrain_scan.depth_fit import Calibration, Pairs, fit, recording_pairs

T = TypeVar("T")


def per_recording(
    refs: list[SampleRef], layout: Layout | Callable[[SampleRef], Layout], read: Callable[[SampleRef, Layout], T]
) -> Iterator[T | str]:
    """``read(ref, its layout)`` of each recording, or the reason it gave nothing (an unreadable file, named).
    ``layout`` is one for every recording, or a function giving each its own
    (``marionette.ingest.survey.recording_layout``)."""
    for ref in refs:
        try:
            yield read(ref, layout(ref) if callable(layout) else layout)
        except SampleError as exc:  # its message names the file
            yield str(exc)
        except (SampleSkipped, OSError, ValueError) as exc:  # SampleSkipped: another species or weapon than the scene's
            yield f"{ref.path}: {exc}"


def iter_pairs(refs: list[SampleRef], layout: Layout | Callable[[SampleRef], Layout], frame_stride: int) -> Iterator[Pairs | str]:
    """Each recording's pairs (``recording_pairs``), or the reason it gave none (``per_recording``)."""
    return per_recording(refs, layout, lambda ref, lay: recording_pairs(ref, lay, frame_stride))


def iter_contact_points(
    refs: list[SampleRef], layout: Layout | Callable[[SampleRef], Layout], decoder: DepthDecoder, frame_stride: int, knobs: dict
) -> Iterator[ContactPoints | str]:
    """Each recording's ``ContactPoints``, or the reason it gave none (``per_recording``)."""
    return per_recording(refs, layout, lambda ref, lay: contact_points(ref, lay, decoder, frame_stride, knobs))


def calibrate_recordings(
    refs: list[SampleRef],
    layout: Layout | Callable[[SampleRef], Layout],
    frame_stride: int = 5,
    family: str = "auto",
    knobs: dict | None = None,
    progress: Callable[[Iterator, int, str], Iterator] = lambda items, total, desc: items,
) -> tuple[Calibration, list[str]]:
    """The calibration of a recording tree: every recording's pairs, the fit (``fit``), then the contact scale
    (``fit_contact_scale``, a second pass) unless ``knobs`` (scan options, ``ScanOptions.scan_kwargs()``) is None;
    and the reasons recordings gave nothing. ``progress(items, total, what)`` wraps each pass (a progress bar)."""
    parts, failed = [], []
    for got in progress(iter_pairs(refs, layout, frame_stride), len(refs), "calibrate-depth"):
        (failed if isinstance(got, str) else parts).append(got)
    cal = fit(Pairs.concat(parts), family)
    if knobs is not None:
        read = iter_contact_points(refs, layout, cal.chosen, frame_stride, knobs)
        cal = cal.with_contact_scale(
            fit_contact_scale([p for p in progress(read, len(refs), "contacts") if not isinstance(p, str)])
        )
    return cal, failed


def plot(cal: Calibration, path: Path, max_points: int = 20000) -> Path:
    """A PNG: the pairs (inliers and outliers) with every fitted curve, and the chosen mapping's residuals."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = cal.pairs
    rng = np.random.default_rng(0)
    idx = rng.permutation(len(p.code))[:max_points]
    inl = cal.fits[cal.best].inliers[idx]
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12, 4.5))
    ax.scatter(p.z[idx][~inl], p.code[idx][~inl], s=2, c="0.75", label="outliers")
    ax.scatter(p.z[idx][inl], p.code[idx][inl], s=2, c="tab:blue", label="inliers")
    for k, f in cal.fits.items():
        if f.decoder is not None:
            ax.plot(f.decoder.depth_of(CODES), CODES, lw=1, label=f"{k} (RMS {f.rms_inliers:.2f})")
    if cal.table is not None:
        ax.plot(cal.table.depth_of(CODES), CODES, "k--", lw=1, label="table")
    ax.set_xscale("log")
    ax.set_xlabel("reference depth (m)")
    ax.set_ylabel("8-bit code")
    ax.legend(fontsize=7)
    zc = cal.chosen.depth_of(np.clip(p.code[idx], 1, 255))
    ax2.scatter(p.z[idx][inl], (zc[inl] - p.z[idx][inl]) / p.z[idx][inl] * 100, s=2)
    ax2.axhline(0, c="k", lw=0.5)
    ax2.set_xscale("log")
    ax2.set_xlabel("reference depth (m)")
    ax2.set_ylabel("decoded − reference (% of depth), inliers")
    fig.suptitle(f"depth calibration: {len(p.code):,} pairs, chosen {cal.chosen.kind}")
    fig.tight_layout()
    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, format="png", dpi=90)
    plt.close(fig)
    return Path(path)
