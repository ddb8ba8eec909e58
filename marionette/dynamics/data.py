"""Training windows for the dynamics model, read from the corpus's dynamics view (20 fps by default).

Everything here is derived from the corpus alone; the definitions, exactly:

**Tokens** (``ActionTokens``). vocab.json numbers the composite action ids densely per entity type
``<rig>:<type_id>`` (the row's ``<entity>.type_id`` column names the type; ``ingest.sample`` keys the
vocab the same way), token 0 = composite 0 = "no valid action". The model has one embedding table
per articulated entity, so an entity's tokens are the concatenation of the vocabularies of every
type of its rig, in increasing type id: entity token 0 = no valid action; type k's vocab token
v ≥ 1 becomes offset_k + v with offset_k = Σ_{types j before k} (size_j − 1). With one type per rig
(the usual case) entity tokens are the vocab tokens. A composite id (or type) the vocab does not
hold is an error naming the segment, the row and the source frame.

**Progress** = motion_frame / clip_length of the row's action (clip length = the largest motion_frame
the corpus saw + 1, from vocab.json), clipped to [0, 1]; 0 for token 0 and for an invalid
motion_frame (−1). It is in source frames: at the source rate it grows by 1/clip_length per frame.
The dynamics view takes discrete fields from the source frame at or before each 20 fps time, i.e.
source frame ⌊1.5·k⌋ of a 30 fps segment, so along a 20 fps clip progress grows by 1 and 2
source frames in turn, 1.5/clip_length per model frame on average (a rollout that advances an
unchanged token should add (source fps / model fps) / clip_length to match what training saw).

**Windows.** A window is W = ``length`` + 1 consecutive dynamics frames of one segment (``length``
model steps plus the next-frame target). Segments shorter than W are skipped (``WindowData.usable``
says which are kept; no padding, so no time mask). Training (``WindowSampler``, train split only):
each epoch draws, from ``numpy.random.default_rng([seed, epoch])``, one phase per usable segment,
uniform in [0, min(W − 1, n − W)], and tiles the segment with non-overlapping windows starting at
phase + k·W; the corpus-wide list of windows is shuffled with the same generator, cut to a multiple
of world_size, and rank r takes every world_size-th window from position r, then full batches of
``batch_size`` (a partial last batch is dropped, so every rank runs the same number of steps).
Ranks therefore see disjoint windows (no frame of one epoch is read by two ranks), and the batches
are a function of (seed, rank, world_size, epoch) alone. Held-out evaluation (``HeldOutWindows``):
every usable segment of the split tiled from frame 0 with stride W, in segment order, rank r taking
every world_size-th window; batches of up to ``batch_size`` (the last may be smaller); frames after a
segment's last whole window are not evaluated.
What "every window of the epoch" means for training: the epoch's windows are the tiles above, and
exactly the first world_size · ⌊⌊E / world_size⌋ / batch_size⌋ · batch_size of the shuffled E are
trained on, each by one rank once; the rest, fewer than world_size · batch_size (E mod world_size
cut for equal shares, then each rank's partial batch), wait for another epoch's draw
(``WindowSampler.epoch_windows`` lists all E in shuffled order).

**Loader workers** (``TrainBatches``, ``train_batches``). A rank's batches from global step s on,
epoch after epoch, numbered j = 0, 1, … from s: in-process (no workers) they are stacked in turn; with
k DataLoader workers, worker w stacks only the batches with j ≡ w (mod k), and the DataLoader, which
asks its workers for batches in turn and returns them in that order (``in_order``), yields the
in-process sequence exactly, so training reads the same batches in the same order (same losses) with
any number of workers. A worker computes the epoch's window list itself from (seed, rank,
world_size, epoch) and reads windows from the memory-mapped cache: what reaches it is the sampler's
recipe (``WindowData`` pickles as its corpus path, split, flags, normaliser and token tables, and
re-opens the arrays when unpickled, under a ``spawn`` start method; ``fork`` shares the open maps),
never the arrays, so k workers add k processes' fixed overhead and no copy of the split.

The normalisation is ``dynamics.normalise``, the relative and terrain features ``dynamics.features``, the window
arrays on disk ``dynamics.windows``.
"""

from __future__ import annotations

from collections.abc import Generator, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from marionette.corpus import MODEL_FPS, Corpus, as_corpus
from marionette.corpus.vocab import ActionTokens, entity_type_key  # noqa: F401 — the models' token tables
from marionette.dynamics.model import PLAYED_OUT_SLACK, Frames
from marionette.dynamics.normalise import Normaliser
from marionette.dynamics.windows import WINDOW_ARRAYS, shard_windows
from marionette.schema import SchemaError

# -- action tokens and progress ----------------------------------------------------------------------


def vocab_sizes(corpus: Corpus | Path | str) -> tuple[int, ...]:
    """Entity vocabulary sizes per articulated entity in layout order (token 0 included), for ``DynamicsConfig``."""
    return ActionTokens.from_corpus(corpus).sizes


# -- windows -----------------------------------------------------------------------------------------


@dataclass
class Batch:
    """A batch of windows: the model's inputs (normalised, float32, batch first, W = length + 1 frames),
    ``terrain_known`` (B, W, N, 132) bool when terrain was loaded, and which windows these are."""

    frames: Frames
    terrain_known: Tensor | None
    segments: tuple[str, ...]
    starts: tuple[int, ...]  # first dynamics frame of each window within its segment


def ended_events(data: WindowData, lengths: tuple[tuple[float, ...], ...], step: float) -> tuple[tuple[float, ...], ...]:
    """``lengths`` (per entity, per token: an event's clip length in source frames, 0 for a loop) with 0 for every
    token that the split's rows show running on where it has played out: a row of the token with at most ``step``
    source frames left, (1 − progress) · length ≤ step, followed by a row of the same token. By the vocab's
    definition an event's motion_frame never wraps, so on a consistent corpus none does; one that does (an action
    replayed back to back, or a motion_frame that stalls) keeps its copy-last odds (``DynamicsConfig.events_end``)."""
    out = [list(t) for t in lengths]
    for i, table in enumerate(lengths):
        L = np.asarray(table, np.float64)
        for tok, prog in zip(data.action, data.progress):
            if len(tok) < 2:
                continue
            cur, nxt = tok[:-1, i], tok[1:, i]
            ended = (L[cur] > 0) & ((1.0 - prog[:-1, i].astype(np.float64)) * L[cur] <= step + PLAYED_OUT_SLACK)
            for t in np.unique(cur[ended & (nxt == cur)]):
                out[i][int(t)] = 0.0
    return tuple(tuple(t) for t in out)


class WindowData:
    """One split's dynamics view, memory-mapped from the window cache: normalised root and body (float32), tokens,
    progress and, when asked, terrain features and the relative feature, per segment (segments in
    ``corpus.segment_ids(split)`` order). A pickle of it holds how to open it, not its arrays."""

    def __init__(
        self,
        corpus: Corpus | Path | str,
        split: str = "train",
        *,
        terrain: bool = False,
        relative: bool = False,
        normaliser: Normaliser | None = None,
        tokens: ActionTokens | None = None,
        fps: float = MODEL_FPS,
        method: str = "linear",
    ):
        c = as_corpus(corpus)
        self.corpus, self.split, self.terrain, self.fps, self.method = c, split, terrain, fps, method
        self.relative = relative
        self.layout = c.layout
        self.normaliser = normaliser or Normaliser.from_corpus(c)
        if self.normaliser.layout_hash != c.layout.hash:
            raise SchemaError(
                f"{c.path}: the normaliser was made for layout {self.normaliser.layout_hash}, the corpus is {c.layout.hash}"
            )
        self.tokens = tokens or ActionTokens.from_corpus(c)
        self.segments: list[str] = c.segment_ids(split)
        rows = {r["segment"]: r for r in c.segments.to_pylist()}
        self.root: list[np.ndarray] = []  # per segment (n, root_dim) float32, normalised
        self.body: list[np.ndarray] = []  # (n, body_dim)
        self.action: list[np.ndarray] = []  # (n, N) int64
        self.progress: list[np.ndarray] = []  # (n, N) float32
        self.features: list[np.ndarray | None] = []  # (n, N, 132) float32
        self.known: list[np.ndarray | None] = []  # (n, N, 132) bool
        self.rel: list[np.ndarray | None] = []  # (n, N, 3) float32, the relative feature
        by_shard: dict[int, list[str]] = {}
        for s in self.segments:
            by_shard.setdefault(int(rows[s]["shard"]), []).append(s)
        loaded: dict[str, tuple] = {}
        for shard, segs in sorted(by_shard.items()):
            arrays, spans = shard_windows(
                c, shard, self.normaliser, self.tokens, terrain=terrain, relative=relative, fps=fps, method=method
            )
            for s in segs:
                if s not in spans:
                    raise SchemaError(f"{c.path}: segment {s} has no rows in the dynamics view of shard {shard}")
                a, b = spans[s]
                loaded[s] = tuple(None if arrays.get(k) is None else arrays[k][a:b] for k in WINDOW_ARRAYS)
        for s in self.segments:
            r, b, t, p, f, k, rl = loaded[s]
            self.root.append(r)
            self.body.append(b)
            self.action.append(t)
            self.progress.append(p)
            self.features.append(f)
            self.known.append(k)
            self.rel.append(rl)
        self.lengths = np.asarray([len(r) for r in self.root], np.int64)

    def __getstate__(self) -> dict[str, Any]:
        """What a pickle holds (a DataLoader worker under ``spawn``): how to open the data, not its arrays."""
        return {
            "corpus": str(self.corpus.path),
            "split": self.split,
            "terrain": self.terrain,
            "relative": self.relative,
            "normaliser": self.normaliser,
            "tokens": self.tokens,
            "fps": self.fps,
            "method": self.method,
        }

    def __setstate__(self, state: dict[str, Any]) -> None:
        """Re-open the pickled data's window arrays, memory-mapped from the cache (computed if it is gone)."""
        corpus, split = state.pop("corpus"), state.pop("split")
        self.__init__(corpus, split, **state)  # type: ignore[misc]

    def usable(self, frames: int) -> list[int]:
        """Indices of the segments holding at least ``frames`` dynamics frames."""
        return [i for i, n in enumerate(self.lengths) if n >= frames]

    def check_window(self, frames: int) -> list[int]:
        """``usable(frames)``, or a ValueError naming the longest segment when none is long enough."""
        if frames < 2:
            raise ValueError(f"a window needs at least 2 frames (length ≥ 1 step), not {frames}")
        ok = self.usable(frames)
        if not ok:
            if not self.segments:
                raise ValueError(f"{self.corpus.path}: split {self.split!r} has no segments")
            i = int(np.argmax(self.lengths))
            raise ValueError(
                f"{self.corpus.path}: a window of {frames} frames (length {frames - 1} + 1) at {self.fps:g} fps is longer "
                f"than every {self.split!r} segment; the longest, {self.segments[i]}, has {self.lengths[i]} frames"
            )
        return ok

    def batch(self, windows: Sequence[tuple[int, int]], frames: int) -> Batch:
        """Stack windows (segment index, first frame) of ``frames`` frames into a ``Batch``."""

        def stack(parts: list[np.ndarray | None]) -> Tensor:
            return torch.from_numpy(np.stack([p[s : s + frames] for p, (_, s) in zip(parts, windows)]))  # type: ignore[index]

        for i, s in windows:
            if s < 0 or s + frames > self.lengths[i]:
                raise IndexError(f"window [{s}, {s + frames}) outside segment {self.segments[i]} of {self.lengths[i]} frames")
        pick = [i for i, _ in windows]
        terrain = known = None
        if self.terrain:
            terrain = stack([self.features[i] for i in pick])  # (B, W, N, 132)
            known = stack([self.known[i] for i in pick])
        frames_ = Frames(
            root=stack([self.root[i] for i in pick]),  # (B, W, root_dim)
            body=stack([self.body[i] for i in pick]),  # (B, W, body_dim)
            tokens=stack([self.action[i] for i in pick]),  # (B, W, N) int64
            progress=stack([self.progress[i] for i in pick]),  # (B, W, N)
            terrain=terrain,
            relative=stack([self.rel[i] for i in pick]) if self.relative else None,  # (B, W, N, 3)
        )
        return Batch(frames_, known, tuple(self.segments[i] for i in pick), tuple(int(s) for _, s in windows))


class WindowSampler:
    """Random training windows of ``length`` steps (+1 frame) from the train split, per (seed, rank,
    world_size, epoch); ranks get disjoint windows and equal batch counts (module doc: the rule)."""

    def __init__(self, data: WindowData, length: int, batch_size: int, *, seed: int = 0, rank: int = 0, world_size: int = 1):
        if data.split != "train":
            raise ValueError(f"training windows come from the train split only; this data is split {data.split!r}")
        if not 0 <= rank < world_size:
            raise ValueError(f"rank {rank} outside world size {world_size}")
        if batch_size < 1:
            raise ValueError(f"batch_size {batch_size} must be ≥ 1")
        self.data, self.length, self.batch_size = data, int(length), int(batch_size)
        self.seed, self.rank, self.world_size = int(seed), int(rank), int(world_size)
        self.frames = self.length + 1
        self.usable = data.check_window(self.frames)
        self.skipped = [data.segments[i] for i in range(len(data.segments)) if i not in set(self.usable)]
        W = self.frames
        fewest = sum((int(n) - min(W - 1, int(n) - W)) // W for n in data.lengths[self.usable])  # every phase at its largest
        if fewest // world_size < batch_size:
            raise ValueError(
                f"{data.corpus.path}: an epoch may hold only {fewest} windows of {W} frames, fewer than "
                f"batch_size {batch_size} × world_size {world_size}; use shorter windows or smaller batches"
            )

    def epoch_windows(self, epoch: int) -> list[tuple[int, int]]:
        """Every window (segment index, first frame) of ``epoch`` over all ranks, in the shuffled order the
        ranks deal from (module doc: which of them are trained on)."""
        rng = np.random.default_rng([self.seed, int(epoch)])
        W, every = self.frames, []
        for i in self.usable:
            n = int(self.data.lengths[i])
            phase = int(rng.integers(0, min(W - 1, n - W) + 1))
            every += [(i, s) for s in range(phase, n - W + 1, W)]
        return [every[k] for k in rng.permutation(len(every))]

    def windows(self, epoch: int) -> list[tuple[int, int]]:
        """This rank's windows (segment index, first frame) of ``epoch``, in batch order."""
        every = self.epoch_windows(epoch)
        per_rank = len(every) // self.world_size
        mine = every[: per_rank * self.world_size][self.rank :: self.world_size]
        return mine[: (per_rank // self.batch_size) * self.batch_size]

    def batches(self, epoch: int) -> int:
        """Number of batches this rank (and every rank) gets in ``epoch``."""
        return len(self.windows(epoch)) // self.batch_size

    def epoch(self, epoch: int) -> Iterator[Batch]:
        """This rank's batches of ``epoch``."""
        wins = self.windows(epoch)
        for k in range(0, len(wins), self.batch_size):
            yield self.data.batch(wins[k : k + self.batch_size], self.frames)

    def stream(self, step: int = 0, part: int = 0, parts: int = 1) -> Iterator[Batch]:
        """This rank's batches from global step ``step`` on, epoch after epoch without end; with ``parts`` > 1
        only the j-th (j = 0, 1, … counted from ``step``) with j ≡ ``part`` (mod ``parts``), the share of
        DataLoader worker ``part`` of ``parts`` (module doc: loader workers)."""
        if not 0 <= part < parts:
            raise ValueError(f"part {part} outside {parts} parts")
        epoch, skip, j, bs = 0, int(step), 0, self.batch_size
        while True:
            wins = self.windows(epoch)
            n = len(wins) // bs
            for k in range(skip, n):
                if j % parts == part:
                    yield self.data.batch(wins[k * bs : (k + 1) * bs], self.frames)
                j += 1
            skip, epoch = max(0, skip - n), epoch + 1


class TrainBatches(IterableDataset):
    """A rank's training batches from global step ``step`` on (``WindowSampler.stream``), for a
    ``DataLoader(batch_size=None)``: in worker w of k only the batches j ≡ w (mod k), which the DataLoader
    interleaves back into the in-process order (module doc: loader workers)."""

    def __init__(self, sampler: WindowSampler, step: int = 0):
        super().__init__()
        self.sampler, self.step = sampler, int(step)

    def __iter__(self) -> Iterator[Batch]:
        info = get_worker_info()
        return self.sampler.stream(self.step) if info is None else self.sampler.stream(self.step, info.id, info.num_workers)


def train_batches(sampler: WindowSampler, step: int = 0, workers: int = 0) -> Generator[Batch, None, None]:
    """The sampler's batches from global step ``step`` on, stacked in this process (``workers`` 0) or by
    ``workers`` DataLoader worker processes; the same batches in the same order either way. Close the
    generator (or drop it) to stop the workers."""
    if workers < 0:
        raise ValueError(f"loader workers must be ≥ 0, not {workers}")
    return sampler.stream(step) if workers == 0 else _loader_batches(sampler, step, workers)


def _loader_batches(sampler: WindowSampler, step: int, workers: int) -> Generator[Batch, None, None]:
    # The loader's own generator: its seed draw leaves torch's global RNG (dropout's) as it was.
    loader = DataLoader(
        TrainBatches(sampler, step), batch_size=None, num_workers=workers, in_order=True, generator=torch.Generator()
    )
    it = iter(loader)
    try:
        yield from it
    finally:
        del it  # the last reference: its workers are shut down now, not at the next garbage collection


class HeldOutWindows:
    """Every whole window of ``length`` steps (+1 frame) of a held-out split, tiled from each segment's
    start, in a fixed order (no randomness); rank r of world_size gets every world_size-th window."""

    def __init__(self, data: WindowData, length: int, batch_size: int, *, rank: int = 0, world_size: int = 1):
        if not 0 <= rank < world_size:
            raise ValueError(f"rank {rank} outside world size {world_size}")
        self.data, self.length, self.batch_size, self.frames = data, int(length), int(batch_size), int(length) + 1
        W = self.frames
        self.usable = data.usable(W) if data.segments else []
        self.skipped = [data.segments[i] for i in range(len(data.segments)) if i not in set(self.usable)]
        every = [(i, s) for i in self.usable for s in range(0, int(data.lengths[i]) - W + 1, W)]
        self._windows = every[rank::world_size]

    def windows(self) -> list[tuple[int, int]]:
        """This rank's windows (segment index, first frame), in order."""
        return list(self._windows)

    def __len__(self) -> int:
        return -(-len(self._windows) // self.batch_size)

    def __iter__(self) -> Iterator[Batch]:
        for k in range(0, len(self._windows), self.batch_size):
            yield self.data.batch(self._windows[k : k + self.batch_size], self.frames)
