"""Training clips for the observation model, streamed from a corpus's video shards with webdataset.

A video shard (``video/shard-NNNNNN.tar``) holds, per 81-frame chunk ``<segment>__c<chunk>``, the RGB
clip ``rgb.mp4`` (the training resolution), its pose-control target ``pose.mkv`` (the bridge's lossless
10-bit G-buffer, same size and frame count) and a ``json``. A *clip* is ``frames`` consecutive frames
(4k + 1, as Wan's VAE expects) of one chunk that holds a pose target, reduced to the model's
``size`` (H, W):

- ``rgb`` (T, 3, H, W) float32 in [−1, 1]: area-averaged (the chunk's size must be a whole multiple of
  ``size``);
- ``pose`` (T, 3, H, W) float32 in [0, 1]: the G-buffer's 10-bit codes / 1023 (height, identity,
  inverse depth), one source pixel per block (``reduce_codes``: the block's bone pixel where it has one),
  so identities stay exact and bones one pixel wide survive the reduction.

Which clip of a chunk: ``start`` = 0 for evaluation (``ClipSource.clips(split, random=False)``); for
training, one start per chunk per epoch drawn from ``numpy.random.default_rng([seed, epoch])`` in the
shard order, uniform in [0, n − frames]. Chunks shorter than ``frames`` and chunks without a pose
target are skipped (counted in ``ClipSource.skipped``). Splits come from ``meta/segments.parquet``.
Tar members are read into memory by webdataset (never extracted), so member names cannot reach the
file system.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import webdataset as wds

from marionette.bridge.gbuffer import CODE_MAX, iter_codes
from marionette.corpus import Corpus
from marionette.corpus.paths import parse_chunk_key
from marionette.ingest.video import decode_frames


@dataclass
class Clip:
    """One training clip: ``rgb`` (T, 3, H, W) in [−1, 1], ``pose`` (T, 3, H, W) in [0, 1], where it came from."""

    rgb: torch.Tensor
    pose: torch.Tensor
    key: str
    start: int
    actions: torch.Tensor | None = None  # (T, N) int64 entity tokens of each frame (the baseline's control)


def _reduce_rgb(frames: np.ndarray, factor: int) -> np.ndarray:
    """(T, H·f, W·f, 3) uint8 → (T, H, W, 3) float32 area means."""
    T, H, W, C = frames.shape
    return frames.reshape(T, H // factor, factor, W // factor, factor, C).mean(axis=(2, 4), dtype=np.float32)


def reduce_codes(codes: np.ndarray, factor: int) -> np.ndarray:
    """(T, H·f, W·f, 3) G-buffer codes → (T, H, W, 3): per f × f block, every channel of the pixel with the largest
    identity code (a bone where the block holds one, so a one-pixel bone survives; the top-left pixel where ties)."""
    T, H, W, C = codes.shape
    h, w = H // factor, W // factor
    blocks = codes.reshape(T, h, factor, w, factor, C).transpose(0, 1, 3, 2, 4, 5).reshape(T, h, w, factor * factor, C)
    pick = blocks[..., 1].argmax(axis=-1)  # first maximum: the top-left pixel of an all-terrain block
    return np.take_along_axis(blocks, pick[..., None, None], axis=3)[:, :, :, 0]


def rgb_frames(frames: np.ndarray, factor: int) -> torch.Tensor:
    """(T, H·f, W·f, 3) uint8 → the model's RGB frames (T, 3, H, W) float32 in [−1, 1] (area means)."""
    rgb = _reduce_rgb(frames, factor) / 127.5 - 1.0
    return torch.from_numpy(np.ascontiguousarray(rgb.transpose(0, 3, 1, 2)))


def pose_frames(codes: np.ndarray, factor: int) -> torch.Tensor:
    """(T, H·f, W·f, 3) G-buffer codes → the model's pose frames (T, 3, H, W) float32 in [0, 1] (``reduce_codes``)."""
    pose = reduce_codes(codes, factor).astype(np.float32) / CODE_MAX
    return torch.from_numpy(np.ascontiguousarray(pose.transpose(0, 3, 1, 2)))


def check_size(src_hw: tuple[int, int], size: tuple[int, int], where: str) -> int:
    """The reduction factor from a chunk's (H, W) to the model's, or a ValueError naming ``where``."""
    (sh, sw), (h, w) = src_hw, size
    if sh % h or sw % w or sh // h != sw // w:
        raise ValueError(f"{where}: a {sh}×{sw} chunk does not reduce to the model's {h}×{w} by one whole factor")
    return sh // h


def decode_clip(sample: dict, frames: int, size: tuple[int, int], start: int) -> Clip:
    """A webdataset sample {"__key__", "rgb.mp4", "pose.mkv", ...} → the clip of ``frames`` frames from ``start``."""
    key = sample["__key__"]
    rgb = np.stack(decode_frames(sample["rgb.mp4"]))  # (n, H, W, 3) uint8
    codes = np.stack(list(iter_codes(sample["pose.mkv"], name=f"{key}.pose.mkv")))  # (n, H, W, 3) uint16
    if codes.shape[:3] != rgb.shape[:3]:
        raise ValueError(f"{key}: pose.mkv {codes.shape[:3]} and rgb.mp4 {rgb.shape[:3]} differ in frames or size")
    if start + frames > len(rgb):
        raise ValueError(f"{key}: a clip of {frames} frames from {start} exceeds the chunk's {len(rgb)}")
    f = check_size(rgb.shape[1:3], size, key)
    return Clip(
        rgb=rgb_frames(rgb[start : start + frames], f), pose=pose_frames(codes[start : start + frames], f), key=key, start=start
    )


def _frame_count(sample: dict) -> int:
    """Frames of a chunk, from its json (one camera intrinsics row per frame)."""
    if "json" not in sample:
        raise ValueError(f"{sample['__key__']}: no json member")
    return len(json.loads(sample["json"])["K"])


class ClipSource:
    """The clips of one split of a corpus's video shards (module doc: which clips)."""

    def __init__(
        self, corpus: Corpus | Path | str, split: str, frames: int, size: tuple[int, int], actions: bool = False
    ) -> None:
        self.corpus = corpus if isinstance(corpus, Corpus) else Corpus(Path(corpus))
        if frames < 1 or (frames - 1) % 4:
            raise ValueError(f"a clip has 4k + 1 frames (Wan's VAE), not {frames}")
        self.split, self.frames, self.size = split, int(frames), (int(size[0]), int(size[1]))
        self.segments = set(self.corpus.segment_ids(split))
        self.shards = sorted(str(p) for p in (self.corpus.path / "video").glob("shard-*.tar"))
        self.skipped: dict[str, str] = {}
        self.actions = actions
        self._tokens: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # segment → (source frames, tokens (n, N))

    def _actions(self, sample: dict, clip: Clip) -> Clip:
        """The clip with the entity tokens of its frames: the chunk json's source frames [a, b) in the segment's rows."""
        from marionette.corpus.vocab import ActionTokens

        seg = parse_chunk_key(clip.key)[0]
        if seg not in self._tokens:
            rows = self.corpus.read_segment(seg)
            tokens, _ = ActionTokens.from_corpus(self.corpus).encode(self.corpus.layout, rows, where=str(self.corpus.path))
            self._tokens[seg] = (rows["frame"].to_numpy(), tokens)
        frames, tokens = self._tokens[seg]
        a = int(json.loads(sample["json"])["frames"][0]) + clip.start
        idx = np.searchsorted(frames, np.arange(a, a + len(clip.rgb)))
        if idx.max() >= len(frames) or not np.array_equal(frames[idx], np.arange(a, a + len(clip.rgb))):
            raise ValueError(f"{clip.key}: source frames {a}..{a + len(clip.rgb) - 1} are not all rows of segment {seg}")
        clip.actions = torch.from_numpy(tokens[idx])
        return clip

    def _samples(self) -> Iterator[dict]:
        if not self.shards:
            return
        # every DDP rank reads every shard (ranks differ in the clips they draw, not in the chunks they hold)
        every_shard = lambda urls: urls  # noqa: E731
        for sample in wds.WebDataset(self.shards, shardshuffle=False, empty_check=False, nodesplitter=every_shard):
            key = sample["__key__"]
            try:
                segment = parse_chunk_key(key, str(sample.get("__url__", "")))[0]
            except ValueError as err:
                self.skipped[str(key)] = str(err)
                continue
            if segment not in self.segments:
                continue
            if "pose.mkv" not in sample:
                self.skipped[key] = "no pose.mkv (render the pose targets first)"
                continue
            n = _frame_count(sample)
            if n < self.frames:
                self.skipped[key] = f"{n} frames, fewer than a clip's {self.frames}"
                continue
            yield sample

    def chunks(self) -> Iterator[Clip]:
        """Every usable chunk whole (all its frames, start 0), reduced to ``size``: what a trainer keeps in
        memory to cut clips from."""
        for sample in self._samples():
            try:
                clip = decode_clip(sample, _frame_count(sample), self.size, 0)
                yield self._actions(sample, clip) if self.actions else clip
            except ValueError as err:
                self.skipped[sample["__key__"]] = str(err)

    def clips(self, seed: int = 0, epoch: int = 0, random: bool = True) -> Iterator[Clip]:
        """Every usable chunk's clip, in shard order; random starts (seeded) or start 0."""
        rng = np.random.default_rng([int(seed), int(epoch)])
        for sample in self._samples():
            n = _frame_count(sample)
            start = int(rng.integers(0, n - self.frames + 1)) if random else 0
            try:
                clip = decode_clip(sample, self.frames, self.size, start)
                yield self._actions(sample, clip) if self.actions else clip
            except ValueError as err:
                self.skipped[sample["__key__"]] = str(err)
