"""Shared fixtures: one session-scoped synthetic source, one corpus built from it, and a copy whose terrain is scanned."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

# Before torch loads its OpenMP runtime (read once, at load; subprocesses inherit it): a thread that waits at a
# barrier sleeps instead of spinning. On a 2-core machine shared with other jobs, two spinning threads made torch's
# training steps up to 9× slower than one thread; sleeping ones are as fast as spinning ones on an idle machine.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("DO_NOT_TRACK", "1")

from marionette.ingest import IngestOptions, VideoSettings, build_corpus  # noqa: E402

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


# The dynamics model needs more play than the session corpus holds (30 s of it): ten 45 s recordings
# at a small resolution (the video is not what it learns from). No terrain scan: the rules-in-the-loop
# and terrain tests use the scanned session corpus.
# 12 minutes of play: with 7.5 (10 recordings) the probe's Force-GT < Force-Shuf count ran 27–43 of 48 over four seeds,
# with 12 it ran 39–42 (docs/tradeoffs.md, "A game with recoveries")
DYNAMICS_SYNTH = {"recordings": 16, "seconds": 45.0, "seed": 11, "width": 96, "height": 54}
DYNAMICS_OPTIONS = IngestOptions(video=VideoSettings(height=36, width=64, chunk_frames=81, crf=28))
TINY_DYNAMICS = {"preset": "tiny", "steps": 1000, "batch_size": 8, "window": 64, "lr": 2e-3, "warmup": 50, "seed": 0}


@pytest.fixture(scope="session")
def dynamics_corpus(tmp_path_factory) -> Path:
    """A corpus of 16 × 45 s synthetic recordings (one recording's segments in the "test" split)."""
    from marionette.corpus import Corpus
    from marionette.synth import generate

    root = tmp_path_factory.mktemp("dynamics")
    generate(root / "recordings", **DYNAMICS_SYNTH, workers=2)
    build_corpus(root / "recordings", root / "corpus", DYNAMICS_OPTIONS, workers=2, progress=False)
    assert Corpus(root / "corpus").segment_ids("test"), "the dynamics corpus needs a held-out split"
    return root / "corpus"


@pytest.fixture(scope="session")
def tiny_dynamics(dynamics_corpus, tmp_path_factory) -> tuple[Path, dict]:
    """The session's one trained tiny checkpoint: (training directory, training summary)."""
    import torch

    from marionette.dynamics.train import TrainConfig, train

    out = tmp_path_factory.mktemp("tiny-dynamics")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the tiny model is overhead-bound: one thread trains it in 2/3 of the time two take
    try:
        summary = train(dynamics_corpus, out, TrainConfig(**TINY_DYNAMICS), log=lambda *_: None)
    finally:
        torch.set_num_threads(threads)
    return out, summary


# The observation model's quality runs, shared by test_observation and test_observation_follow: 18×32 (the 36×64
# chunks halved), 5-frame clips; a fifth of the pose model's clips are given another chunk's first frame, none of
# the baseline's. Both train on the dynamics corpus with its terrain scanned and pose targets rendered.
OBS_SIZE = (18, 32)
OBS_SCAN_STRIDE = 4  # the stage's terrain from every 4th depth frame (3,400 of 13,500): a quarter of the scan's time


def obs_config():
    from marionette.observation.train import ObservationTrainConfig

    return ObservationTrainConfig(preset="tiny", steps=300, batch_size=4, frames=5, reduce=2, patch=2, lr=1e-3, warmup=20)


@pytest.fixture(scope="session")
def follow_corpus(dynamics_corpus, tmp_path_factory) -> Path:
    """A copy of the dynamics corpus with its terrain scanned (the background behind moved bodies) and pose targets
    rendered."""
    from marionette.bridge.targets import render_pose_targets
    from terrain_scan.scan import ScanOptions, scan_stages

    out = tmp_path_factory.mktemp("follow") / "corpus"
    shutil.copytree(dynamics_corpus, out)
    scan_stages(out, incremental=True, options=ScanOptions(frame_stride=OBS_SCAN_STRIDE), log=lambda *_: None)
    render_pose_targets(out)
    return out


@pytest.fixture(scope="session")
def pose_run(follow_corpus, tmp_path_factory) -> tuple[Path, dict]:
    """The pose-controlled observation model trained on ``follow_corpus``: (run directory, training summary)."""
    from marionette.observation.train import train

    out = tmp_path_factory.mktemp("follow-pose")
    return out, train(follow_corpus, out, obs_config(), log=lambda *_: None)


@pytest.fixture(scope="session")
def baseline_run(follow_corpus, tmp_path_factory) -> tuple[Path, dict]:
    """The pixel-AR baseline (action schedules, no pose video) trained on ``follow_corpus`` with the same recipe."""
    from dataclasses import replace

    from marionette.observation.train import train

    out = tmp_path_factory.mktemp("follow-baseline")
    return out, train(follow_corpus, out, replace(obs_config(), control="actions"), log=lambda *_: None)
