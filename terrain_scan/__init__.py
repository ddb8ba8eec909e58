"""Layered height-field terrain scanning (TRN2 chunks)."""
