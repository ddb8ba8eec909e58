"""Recordings as a game writes them: the WildWorld sample layout (``wildworld``), read for a scene layout, below
every package that reads recordings (ingest, the terrain scan, calibration, the survey)."""
