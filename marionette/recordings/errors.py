"""What reading one recording can raise: the sample cannot be ingested (quarantined), or it lies outside the slice
asked for (listed); and the check every input file of a recording passes before it is opened."""

from __future__ import annotations

from pathlib import Path

from marionette.io import regular_file


class SampleError(ValueError):
    """A sample cannot be ingested; the message names the file and row or frame."""


class SampleSkipped(Exception):
    """A sample lies outside the requested slice (species, weapon); it is listed, not quarantined."""


def regular_input(path: Path) -> None:
    """A ``SampleError`` naming ``path`` unless it is a regular file (a FIFO or device would block, or never end, the
    read that follows; refused from its stat)."""
    try:
        regular_file(path)
    except ValueError as exc:
        raise SampleError(str(exc)) from None
