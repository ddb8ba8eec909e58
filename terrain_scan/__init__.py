"""Layered height-field terrain scanning (TRN2 chunks): accumulate, merge, fill, store, query, mesh."""
