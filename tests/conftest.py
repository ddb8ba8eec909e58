"""Shared fixtures: one session-scoped synthetic source, one corpus built from it, and a copy whose terrain is scanned."""

from __future__ import annotations

import multiprocessing
import os
import shutil
from concurrent.futures import Future, ProcessPoolExecutor
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
def dynamics_corpus(request, tmp_path_factory) -> Path:
    """A corpus of 16 × 45 s synthetic recordings (one recording's segments in the "test" split)."""
    from marionette.corpus import Corpus
    from marionette.synth import generate

    root = tmp_path_factory.mktemp("dynamics")
    generate(root / "recordings", **DYNAMICS_SYNTH, workers=2)
    build_corpus(root / "recordings", root / "corpus", DYNAMICS_OPTIONS, workers=2, progress=False)
    assert Corpus(root / "corpus").segment_ids("test"), "the dynamics corpus needs a held-out split"
    if any(OBSERVATION_FIXTURES & set(getattr(item, "fixturenames", ())) for item in request.session.items):
        observation_jobs(root / "corpus", tmp_path_factory)  # start them now, in the background
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


# The observation fixtures below take about four minutes of one core, mostly single-threaded (a terrain scan, a GL
# render, two small trainings), so once the dynamics corpus exists they are made in one background process while
# the session goes on (the dynamics model trains on one thread meanwhile), and each fixture waits for its result.
OBSERVATION_FIXTURES = {"follow_corpus", "pose_run", "baseline_run"}
_jobs: dict[str, Future] = {}
_pool: ProcessPoolExecutor | None = None


def _silent(*_) -> None:
    pass


def _prepare_follow(dynamics: Path, out: Path) -> Path:
    """``follow_corpus``'s work: the copy, its scan, its pose targets."""
    from marionette.bridge.targets import render_pose_targets
    from terrain_scan.scan import ScanOptions, scan_stages

    shutil.copytree(dynamics, out)
    scan_stages(out, incremental=True, options=ScanOptions(frame_stride=OBS_SCAN_STRIDE), log=_silent)
    render_pose_targets(out)
    return out


def _train_observation(corpus: Path, out: Path, control: str) -> tuple[Path, dict]:
    """``pose_run`` / ``baseline_run``'s work, on one thread (the session's tests use the other core)."""
    from dataclasses import replace

    import torch

    from marionette.observation.train import train

    torch.set_num_threads(1)
    return out, train(corpus, out, replace(obs_config(), control=control), log=_silent)


def observation_jobs(dynamics: Path, tmp_path_factory) -> dict[str, Future]:
    """The background jobs of the observation fixtures (started once; later calls return them)."""
    global _pool
    if not _jobs:
        _pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"))
        follow = tmp_path_factory.mktemp("follow") / "corpus"
        _jobs["follow_corpus"] = _pool.submit(_prepare_follow, dynamics, follow)
        for name, control in (("baseline_run", "actions"), ("pose_run", "pose")):  # in the order the tests ask
            _jobs[name] = _pool.submit(_train_observation, follow, tmp_path_factory.mktemp(name.replace("_run", "")), control)
    return _jobs


def pytest_sessionfinish(session, exitstatus) -> None:
    if _pool is not None:
        for proc in list(getattr(_pool, "_processes", {}).values()):  # a run cut short leaves no job running
            proc.terminate()
        _pool.shutdown(wait=False, cancel_futures=True)


@pytest.fixture(scope="session")
def follow_corpus(dynamics_corpus, tmp_path_factory) -> Path:
    """A copy of the dynamics corpus with its terrain scanned (the background behind moved bodies) and pose targets
    rendered (made in the background, ``observation_jobs``)."""
    return observation_jobs(dynamics_corpus, tmp_path_factory)["follow_corpus"].result()


@pytest.fixture(scope="session")
def pose_run(follow_corpus, dynamics_corpus, tmp_path_factory) -> tuple[Path, dict]:
    """The pose-controlled observation model trained on ``follow_corpus``: (run directory, training summary)."""
    return observation_jobs(dynamics_corpus, tmp_path_factory)["pose_run"].result()


@pytest.fixture(scope="session")
def baseline_run(follow_corpus, dynamics_corpus, tmp_path_factory) -> tuple[Path, dict]:
    """The pixel-AR baseline (action schedules, no pose video) trained on ``follow_corpus`` with the same recipe."""
    return observation_jobs(dynamics_corpus, tmp_path_factory)["baseline_run"].result()
