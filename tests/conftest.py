"""Shared fixtures: one session-scoped synthetic source, one corpus built from it, and a copy whose terrain is scanned."""

from __future__ import annotations

import os
import shutil
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


@pytest.fixture(scope="session")
def scanned_corpus(corpus, tmp_path_factory) -> Path:
    """A copy of ``corpus`` with its stage's terrain scanned. Tests read it; a test that changes it copies
    it first (``scanned_copy``)."""
    from terrain_scan.scan import scan_stages

    out = tmp_path_factory.mktemp("scanned") / "corpus"
    shutil.copytree(corpus, out)
    scan_stages(out, incremental=True, log=lambda *_: None)
    return out


@pytest.fixture(scope="module")
def scanned_copy(scanned_corpus, tmp_path_factory) -> Path:
    """A module's own copy of ``scanned_corpus``, free to change."""
    out = tmp_path_factory.mktemp("scanned-copy") / "corpus"
    shutil.copytree(scanned_corpus, out)
    return out
