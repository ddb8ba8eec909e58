"""Training clips for the observation model, streamed from a corpus's video shards with webdataset.

A video shard (``video/shard-NNNNNN.tar``) holds, per 81-frame chunk ``<segment>__c<chunk>``, the RGB
clip ``rgb.mp4`` (the training resolution) and a ``json``; its pose shard (``pose/shard-NNNNNN.tar``)
the chunk's pose-control target ``pose.gbz`` (the bridge's lossless 10-bit G-buffer, same size and frame
count), joined by key as the video shard streams past (``video_shards.PoseShard``: one pose shard open at
a time, a member read when its chunk comes; a stale target is not joined). A *clip* is ``frames`` consecutive frames
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
import os
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import webdataset as wds

from marionette.bridge.gbuffer import CODE_MAX, iter_codes
from marionette.bridge.jitter import Jitter
from marionette.chunks import is_clip_length
from marionette.corpus import Corpus, paths
from marionette.corpus.paths import SHARD_NAME, parse_chunk_key
from marionette.corpus.video_shards import POSE_KIND, RGB_KIND, PoseShard, member_index, read_at
from marionette.corpus.vocab import ActionTokens
from marionette.distributed import rank_world
from marionette.video import decode_frames


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
    """A webdataset sample {"__key__", "rgb.mp4", "pose.gbz", ...} → the clip of ``frames`` frames from ``start``."""
    key = sample["__key__"]
    rgb = np.stack(decode_frames(sample[RGB_KIND]))  # (n, H, W, 3) uint8
    codes = np.stack(list(iter_codes(sample[POSE_KIND], name=f"{key}.{POSE_KIND}")))  # (n, H, W, 3) uint16
    if codes.shape[:3] != rgb.shape[:3]:
        raise ValueError(f"{key}: {POSE_KIND} {codes.shape[:3]} and {RGB_KIND} {rgb.shape[:3]} differ in frames or size")
    if start + frames > len(rgb):
        raise ValueError(f"{key}: a clip of {frames} frames from {start} exceeds the chunk's {len(rgb)}")
    f = check_size(rgb.shape[1:3], size, key)
    return Clip(
        rgb=rgb_frames(rgb[start : start + frames], f), pose=pose_frames(codes[start : start + frames], f), key=key, start=start
    )


def jittered_targets(corpus: Corpus, root_m: float, joint_deg: float, time_s: float, seed: int, log=print) -> str | None:
    """The key of the pose targets of state jittered by these amounts (``bridge.jitter``), rendered first where
    missing (rank 0, the other ranks waiting); None when every amount is 0 (the corpus's own targets)."""

    jitter = Jitter(root_m, joint_deg, time_s, seed)
    if not jitter.active:
        return None
    rank, world = rank_world()
    if rank == 0:
        from marionette.bridge.targets import render_pose_targets

        report = render_pose_targets(corpus.path, jitter=jitter)
        log(f"pose targets of jittered state ({jitter}): {len(report.rendered)} chunks rendered, {len(report.failed)} failed")
    if world > 1:
        torch.distributed.barrier()
    return jitter.key()


class ClipSource:
    """The clips of one split of a corpus's video shards (module doc: which clips)."""

    def __init__(
        self,
        corpus: Corpus | Path | str,
        split: str,
        frames: int,
        size: tuple[int, int],
        actions: bool = False,
        jitter: str | None = None,
    ) -> None:
        self.corpus = corpus if isinstance(corpus, Corpus) else Corpus(Path(corpus))
        self.jitter = jitter  # the key of a jitter whose pose targets to read (bridge.jitter), else the corpus's own
        if not is_clip_length(frames, minimum=1):
            raise ValueError(f"a clip has 4k + 1 frames (Wan's VAE), not {frames}")
        self.split, self.frames, self.size = split, int(frames), (int(size[0]), int(size[1]))
        self.segments = set(self.corpus.segment_ids(split))
        self.shards = sorted(
            str(p) for p in paths.video_dir(self.corpus.path).glob("shard-*.tar") if SHARD_NAME.fullmatch(p.stem)
        )
        self.skipped: dict[str, str] = {}
        self.actions = actions
        self._tokens: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # segment → (source frames, tokens (n, N))

    def _actions(self, sample: dict, clip: Clip) -> Clip:
        """The clip with the entity tokens of its frames: the chunk json's source frames [a, b) in the segment's rows."""
        return self._actions_from(int(json.loads(sample["json"])["frames"][0]), clip)

    def _actions_from(self, first_frame: int, clip: Clip) -> Clip:
        """The clip with the entity tokens of its frames, its chunk starting at source frame ``first_frame``."""

        seg = parse_chunk_key(clip.key)[0]
        if seg not in self._tokens:
            rows = self.corpus.read_segment(seg)
            tokens, _ = ActionTokens.from_corpus(self.corpus).encode(self.corpus.layout, rows, where=str(self.corpus.path))
            self._tokens = {seg: (rows["frame"].to_numpy(), tokens)}  # chunks of a segment are consecutive
        frames, tokens = self._tokens[seg]
        a = first_frame + clip.start
        idx = np.searchsorted(frames, np.arange(a, a + len(clip.rgb)))
        if idx.max() >= len(frames) or not np.array_equal(frames[idx], np.arange(a, a + len(clip.rgb))):
            raise ValueError(f"{clip.key}: source frames {a}..{a + len(clip.rgb) - 1} are not all rows of segment {seg}")
        clip.actions = torch.from_numpy(tokens[idx])
        return clip

    def _pose_shard(self, n: int) -> tuple[PoseShard, str] | None:
        """Video shard ``n``'s pose shard (open) and the state shard's ingest hash; None, the reason in ``skipped``,
        where the pose shard is refused (untrusted input: its chunks are skipped)."""
        path = self.corpus.pose_path(n, self.jitter)
        try:
            return PoseShard(path), self.corpus.shard_hash(n)
        except (ValueError, KeyError) as err:
            self.skipped[path.name] = str(err)
            return None

    def _usable(self, key: str, chunk_json: bytes | None, pose: tuple[PoseShard, str] | None) -> tuple[Any, int, int] | None:
        """(current ``pose.gbz`` member, frame count, first source frame) of a chunk a clip can come from; None, the reason in
        ``skipped``, for a chunk without a json member or a current pose target, or shorter than a clip. The one rule
        both readers (``_samples``, ``index``) apply."""
        try:
            got = pose[0].member(key, chunk_json, pose[1]) if pose is not None and chunk_json is not None else None
            if got is None:
                self.skipped[key] = f"no current {POSE_KIND} (render the pose targets first)"
                return None
            rec = json.loads(chunk_json)
            frames, first = len(rec["K"]), int(rec["frames"][0])  # one intrinsics row per frame
        except (ValueError, KeyError, TypeError, IndexError) as err:
            self.skipped[key] = f"not a chunk record or pose target: {type(err).__name__}: {err}"
            return None
        if frames < self.frames:
            self.skipped[key] = f"{frames} frames, fewer than a clip's {self.frames}"
            return None
        return got[1], frames, first

    def _samples(self) -> Iterator[tuple[dict, int]]:
        """(webdataset sample with its ``pose.gbz`` joined, frame count) of every usable chunk, streamed in shard order."""
        if not self.shards:
            return
        # every DDP rank reads every shard (ranks differ in the clips they draw, not in the chunks they hold)
        every_shard = lambda urls: urls  # noqa: E731
        url, pose = None, None  # the video shard streaming past, its pose shard and state hash
        try:
            for sample in wds.WebDataset(self.shards, shardshuffle=False, empty_check=False, nodesplitter=every_shard):
                key = sample["__key__"]
                sample.pop(POSE_KIND, None)  # a video shard written before pose shards: its targets are not joined
                try:
                    segment = parse_chunk_key(key, str(sample.get("__url__", "")))[0]
                except ValueError as err:
                    self.skipped[str(key)] = str(err)
                    continue
                if segment not in self.segments:
                    continue
                if url != sample["__url__"]:
                    if pose is not None:
                        pose[0].close()
                    url = sample["__url__"]
                    pose = self._pose_shard(int(SHARD_NAME.fullmatch(Path(url).stem)["n"]))
                use = self._usable(key, sample.get("json"), pose)
                if use is not None:
                    sample[POSE_KIND] = pose[0].read(use[0])
                    yield sample, use[1]
        finally:
            if pose is not None:
                pose[0].close()

    def index(self) -> list[ChunkRef]:
        """Where every usable chunk's bytes are (the chunks ``chunks`` yields, in the same order, under the same
        rules), from the shards' member headers and json members only; nothing is decoded. Grows with the number
        of chunks (a few hundred bytes each), not with their frames."""
        refs: list[ChunkRef] = []
        for url in self.shards:
            vpath = Path(url)
            n = int(SHARD_NAME.fullmatch(vpath.stem)["n"])
            try:
                members = member_index(vpath)
            except ValueError as err:
                self.skipped[vpath.name] = str(err)
                continue
            wanted = {k: m for k, m in members.items() if parse_chunk_key(k)[0] in self.segments}
            if not wanted or (pose := self._pose_shard(n)) is None:
                continue
            ppath = self.corpus.pose_path(n, self.jitter)
            stamp = (*_stamp(vpath), *_stamp(ppath))
            with pose[0]:
                for key, m in wanted.items():
                    if RGB_KIND not in m:
                        self.skipped[key] = "no rgb.mp4 member"
                        continue
                    data = read_at(vpath, m["json"].offset_data, m["json"].size) if "json" in m else None
                    use = self._usable(key, data, pose)
                    if use is None:
                        continue
                    target, frames, first = use
                    rgb = m[RGB_KIND]
                    at = ((rgb.offset_data, rgb.size), (target.offset_data, target.size))
                    refs.append(ChunkRef(key, str(vpath), str(ppath), *at, frames, first, stamp))
        return refs

    def chunk(self, ref: ChunkRef) -> Clip:
        """One indexed chunk whole (all its frames, start 0) at ``size``, read from where ``index`` found it; a shard
        rewritten since is a ValueError naming it."""
        if (*_stamp(Path(ref.video)), *_stamp(Path(ref.pose))) != ref.stamp:
            raise ValueError(f"{ref.video}: the video or pose shard of chunk {ref.key} changed since it was indexed")
        sample = {
            "__key__": ref.key,
            RGB_KIND: read_at(Path(ref.video), *ref.rgb_at),
            POSE_KIND: read_at(Path(ref.pose), *ref.pose_at),
        }
        clip = decode_clip(sample, ref.frames, self.size, 0)
        return self._actions_from(ref.first_frame, clip) if self.actions else clip

    def chunks(self) -> Iterator[Clip]:
        """Every usable chunk whole (all its frames, start 0), reduced to ``size``: what a trainer keeps in
        memory to cut clips from."""
        for sample, n in self._samples():
            try:
                clip = decode_clip(sample, n, self.size, 0)
                yield self._actions(sample, clip) if self.actions else clip
            except ValueError as err:
                self.skipped[sample["__key__"]] = str(err)

    def clips(self, seed: int = 0, epoch: int = 0, random: bool = True) -> Iterator[Clip]:
        """Every usable chunk's clip, in shard order; random starts (seeded) or start 0."""
        rng = np.random.default_rng([int(seed), int(epoch)])
        for sample, n in self._samples():
            start = int(rng.integers(0, n - self.frames + 1)) if random else 0
            try:
                clip = decode_clip(sample, self.frames, self.size, start)
                yield self._actions(sample, clip) if self.actions else clip
            except ValueError as err:
                self.skipped[sample["__key__"]] = str(err)


def _stamp(path: Path) -> tuple[int, int]:
    """(size, mtime in ns) of a file, (−1, −1) where there is none."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return (-1, -1)
    return (st.st_size, st.st_mtime_ns)


@dataclass(frozen=True)
class ChunkRef:
    """Where one usable chunk's bytes are: its video and pose shards, (offset, size) of its ``rgb.mp4`` and
    ``pose.gbz`` members, its frame count and first source frame, and (size, mtime) of both shards when indexed."""

    key: str
    video: str
    pose: str
    rgb_at: tuple[int, int]
    pose_at: tuple[int, int]
    frames: int
    first_frame: int
    stamp: tuple[int, int, int, int]


class ChunkStore:
    """The indexed chunks of a ``ClipSource`` as a sequence of whole ``Clip``s: a chunk is decoded when it is first
    asked for and kept while the decoded chunks fit in ``budget_bytes`` (least recently used evicted first). What a
    reader gets does not depend on the budget; memory does not grow with the corpus beyond the budget and the
    index."""

    def __init__(self, source: ClipSource, refs: list[ChunkRef] | None = None, budget_bytes: int = 2 << 30):
        if budget_bytes < 0:
            raise ValueError(f"budget_bytes must be ≥ 0, not {budget_bytes}")
        self.source, self.budget = source, int(budget_bytes)
        self.refs = source.index() if refs is None else list(refs)
        self._cache: OrderedDict[int, Clip] = OrderedDict()
        self.held_bytes = 0
        self.decoded = 0  # decodes so far (hits are not counted)

    def __len__(self) -> int:
        return len(self.refs)

    def __getitem__(self, i: int) -> Clip:
        i = int(i)
        if not -len(self.refs) <= i < len(self.refs):
            raise IndexError(f"chunk {i} of {len(self.refs)}")
        i %= len(self.refs)
        if i in self._cache:
            self._cache.move_to_end(i)
            return self._cache[i]
        clip = self.source.chunk(self.refs[i])
        self.decoded += 1
        size = _clip_bytes(clip)
        if size <= self.budget:
            self._cache[i] = clip
            self.held_bytes += size
            while self.held_bytes > self.budget:
                _, old = self._cache.popitem(last=False)
                self.held_bytes -= _clip_bytes(old)
        return clip

    def __iter__(self) -> Iterator[Clip]:
        for i in range(len(self.refs)):
            yield self[i]


def _clip_bytes(clip: Clip) -> int:
    return sum(t.numel() * t.element_size() for t in (clip.rgb, clip.pose, clip.actions) if t is not None)
