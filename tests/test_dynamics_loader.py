"""The dynamics loader's DataLoader path: worker processes hand back the in-process batches in the in-process order
over memory-mapped window arrays, 2 ranks × 2 workers train on every window of an epoch once, and training reads the
same batches with workers as without. That its memory does not grow with the corpus is measured by
``benchmarks/bench_memory.py`` (docs/tradeoffs.md)."""

from __future__ import annotations

import itertools
import json
import pickle
from dataclasses import replace

import pytest
import torch

from marionette.checkpoint import latest_checkpoint
from marionette.dynamics.config import TrainConfig
from marionette.dynamics.data import TrainBatches, WindowData, WindowSampler, train_batches
from marionette.dynamics.train import main, train


def ids(batches) -> list[tuple[str, int]]:
    """The windows (segment, first frame) of batches, in order."""
    return [w for b in batches for w in zip(b.segments, b.starts, strict=True)]


@pytest.mark.filterwarnings("ignore:This DataLoader will create 3 worker processes")
def test_workers_hand_back_the_in_process_batches(dynamics_corpus):
    """From a step inside epoch 0 across the start of epoch 2: 2 workers (each stacking every other batch)
    yield the in-process batches, equal tensor for tensor, in the same order; 3 workers (every third batch
    each) too. What a worker is sent under ``spawn`` is the sampler's recipe, a few KB, which re-opens the
    same memory-mapped arrays."""
    data = WindowData(dynamics_corpus, terrain=True)
    sampler = WindowSampler(data, 16, 8, seed=1, rank=1, world_size=2)
    step = 5
    n = sampler.batches(0) + sampler.batches(1) - step + 3
    serial = list(itertools.islice(train_batches(sampler, step), n))
    for k in (2, 3):
        loader = train_batches(sampler, step, workers=k)
        got = list(itertools.islice(loader, n))
        loader.close()
        assert ids(got) == ids(serial)
        for a, b in zip(got, serial, strict=True):
            assert all(torch.equal(getattr(a.frames, f), getattr(b.frames, f)) for f in ("root", "body", "tokens", "terrain"))
            assert torch.equal(a.terrain_known, b.terrain_known)
    blob = pickle.dumps(TrainBatches(sampler, step))
    assert len(blob) < 64 << 10, len(blob)  # the split's arrays are ~19 MB
    again = pickle.loads(blob)  # our own object, pickled above, as a spawned DataLoader worker receives it: never data
    assert type(again.sampler.data.body[0]).__name__ == "memmap" and ids(itertools.islice(iter(again), 4)) == ids(serial[:4])
    with pytest.raises(ValueError, match="loader_workers"):
        TrainConfig(loader_workers=-1)


def test_every_window_once_over_two_ranks_and_two_workers(dynamics_corpus):
    """Epoch 0 over 2 ranks × 2 DataLoader workers: no window twice, and the windows trained on are exactly
    the epoch's shuffled list (``epoch_windows``, E windows) but its last E − 2 · 4 · batches, which are
    fewer than world_size × batch_size = 8 (E mod 2 cut for equal shares, then each rank's partial
    batch). With a seed whose E divides by 8, nothing is dropped: every window of the epoch once."""
    data = WindowData(dynamics_corpus)
    world, bs = 2, 4

    def epoch_over_ranks(seed: int) -> tuple[list[tuple[str, int]], list[tuple[str, int]]]:
        got = []
        for rank in range(world):
            sampler = WindowSampler(data, 16, bs, seed=seed, rank=rank, world_size=world)
            loader = train_batches(sampler, 0, workers=2)
            got += ids(itertools.islice(loader, sampler.batches(0)))
            loader.close()
        return got, [(data.segments[i], s) for i, s in sampler.epoch_windows(0)]

    got, every = epoch_over_ranks(0)
    assert len(set(got)) == len(got) and set(got) <= set(every)
    dropped = set(every) - set(got)
    assert set(every[: len(got)]) == set(got) and dropped == set(every[len(got) :])
    assert len(got) % (world * bs) == 0 and len(dropped) < world * bs
    even = next(s for s in range(1, 200) if len(WindowSampler(data, 16, bs, seed=s).epoch_windows(0)) % (world * bs) == 0)
    got, every = epoch_over_ranks(even)
    assert sorted(got) == sorted(every)
    print(f"\nepoch 0: {len(got)} windows, each once over 2 ranks × 2 workers (seed {even}); seed 0 left {len(dropped)}")


def test_training_with_loader_workers_is_bit_identical(dynamics_corpus, tmp_path):
    """3 steps of a tiny config with dropout, in-process and with ``--loader-workers 2`` (the command's flag):
    the same losses, gradient norms and weights, bit for bit; a run stopped after 2 steps with workers resumes
    without them onto the same sequence."""
    cfg = TrainConfig(preset="tiny", steps=3, batch_size=4, window=16, warmup=1, dropout=0.1, seed=2, eval_batch_size=256)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        serial = train(dynamics_corpus, tmp_path / "serial", cfg, log=lambda *_: None)
        flags = ["--preset", "tiny", "--steps", "3", "--batch-size", "4", "--window", "16", "--warmup", "1"]
        flags += ["--dropout", "0.1", "--seed", "2", "--eval-batch-size", "256", "--loader-workers", "2", "--no-progress"]
        workers = main([str(dynamics_corpus), "--out", str(tmp_path / "workers"), *flags])
        train(dynamics_corpus, tmp_path / "resumed", replace(cfg, loader_workers=2), log=lambda *_: None, stop_at=2)
        resumed = train(dynamics_corpus, tmp_path / "resumed", cfg, log=lambda *_: None)
    finally:
        torch.set_num_threads(threads)
    meta = json.loads((latest_checkpoint(tmp_path / "workers") / "meta.json").read_text())
    assert meta["train_config"]["loader_workers"] == 2
    assert workers["losses"] == serial["losses"] and resumed["losses"] == serial["losses"]
    assert workers["eval"] == serial["eval"]
