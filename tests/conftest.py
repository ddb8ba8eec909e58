"""The suite's plugins (tests/fixtures/): shared corpora and models built once per run, the tiers, the budget."""

from __future__ import annotations

import os

# Before torch loads its OpenMP runtime (read once, at load; subprocesses inherit it): a thread that waits at a
# barrier sleeps instead of spinning. On a 2-core machine shared with other jobs, two spinning threads made torch's
# training steps up to 9× slower than one thread; sleeping ones are as fast as spinning ones on an idle machine.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("DO_NOT_TRACK", "1")
# Every process the suite starts (xdist's workers, the builder, each torchrun rank, Prefect flow run, Dask worker and CLI
# call) caches the bytecode it compiles: uv installs site-packages without it, so on a machine that sets
# PYTHONDONTWRITEBYTECODE each of them compiled prefect, diffusers, peft, matplotlib and the project again (4 s a
# process importing the observation model's stack; the Wan training tests took 10 % less CPU).
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
if os.environ.get("PYTEST_XDIST_WORKER"):
    # Two workers and the background builder share two cores: one thread each keeps torch's threads from waiting on
    # one another (the models the suite trains are small enough that a second thread buys little).
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    # Mesa's llvmpipe rasterises the bridge's small test frames in the calling thread: its worker threads cost more
    # than they save at 36 × 64 (the dynamics corpus's pose targets: 7.6 s against 11.0 s for 4,300 frames).
    os.environ.setdefault("LP_NUM_THREADS", "0")

pytest_plugins = ["pytester", "fixtures.corpora", "fixtures.models", "fixtures.browser", "fixtures.tiers", "fixtures.budget"]
