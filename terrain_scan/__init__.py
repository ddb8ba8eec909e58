"""Layered height-field terrain scanning (TRN2 chunks): accumulate, merge, fill, store, query, mesh."""

from terrain_scan.field import LayeredField, open_stage

__all__ = ["LayeredField", "open_stage"]
