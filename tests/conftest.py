"""Shared fixtures: one session-scoped synthetic source and one corpus built from it."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from marionette.ingest import IngestOptions, VideoSettings, build_corpus

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("DO_NOT_TRACK", "1")

SYNTH = {"recordings": 3, "seconds": 10.0, "seed": 7, "width": 160, "height": 90}
TEST_OPTIONS = IngestOptions(video=VideoSettings(height=72, width=128, chunk_frames=81, crf=23))


@pytest.fixture(scope="session")
def synth_source(tmp_path_factory) -> Path:
    from marionette.synth import generate

    root = tmp_path_factory.mktemp("synth")
    generate(root, **SYNTH, workers=2)
    return root


@pytest.fixture(scope="session")
def corpus(synth_source, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("corpus") / "corpus"
    build_corpus(synth_source, out, TEST_OPTIONS, workers=2, progress=False)
    return out
