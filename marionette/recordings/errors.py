"""What reading one recording can raise: the sample cannot be ingested (quarantined), or it lies outside the slice
asked for (listed)."""

from __future__ import annotations


class SampleError(ValueError):
    """A sample cannot be ingested; the message names the file and row or frame."""


class SampleSkipped(Exception):
    """A sample lies outside the requested slice (species, weapon); it is listed, not quarantined."""
