"""Ingest: WildWorld samples → state shards (Arrow) and video shards (webdataset), then finalize.

``build_corpus`` is the whole stage in one process pool (the CLI); the Prefect flow
``build-corpus`` fans the same ``ingest_sample`` calls out over Dask and then calls ``finalize``.
"""

from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

from marionette.corpus import paths
from marionette.corpus.lock import corpus_lock
from marionette.corpus.stages import MAX_STAGES_BYTES, check_stage_map
from marionette.fanout import threads_per_worker
from marionette.ingest.finalize import finalize, finish_pending
from marionette.ingest.sample import (
    IngestOptions,
    SampleResult,
    check_keys,
    file_digests,
    ingest_sample,
    input_hash,
    known_record,
    sample_inputs,
    sample_key,
    split_of,
)
from marionette.io import read_json
from marionette.recordings.errors import SampleError
from marionette.recordings.wildworld import RGB_FILE, SKELETON_FILE, STAGES_FILE, STATE_FILE, SampleRef, discover, read_sample
from marionette.schema import SchemaError
from marionette.video import VideoSettings

__all__ = [
    "IngestOptions",
    "SampleError",
    "SampleRef",
    "SampleResult",
    "VideoSettings",
    "build_corpus",
    "check_keys",
    "check_corpus_options",
    "check_source",
    "corpus_lock",
    "finish_pending",
    "discover",
    "file_digests",
    "finalize",
    "ingest_sample",
    "input_hash",
    "known_record",
    "load_stage_map",
    "read_sample",
    "sample_inputs",
    "sample_key",
    "split_of",
]


def load_stage_map(source: Path) -> dict[str, str]:
    """Optional ``stages.json`` in the source root: recording id (``part/id``) → stage id."""
    p = Path(source) / STAGES_FILE
    if not p.exists():
        return {}
    return check_stage_map(read_json(p, MAX_STAGES_BYTES), str(p))


def check_corpus_options(corpus: Path, options: IngestOptions) -> None:
    """Refuse to add samples of one scene layout to a corpus built for another."""
    info = paths.meta(corpus, paths.INFO)
    if info.exists():
        d = read_json(info)
        have_scene = d.get("ingest", {}).get("scene")
        if options.auto or have_scene == "auto":
            if have_scene != options.scene:
                raise SchemaError(
                    f"{corpus}: the corpus was built with scene {have_scene!r}; this build asks for {options.scene!r} "
                    "(a corpus of one scene, or one where each recording has its own: not both)"
                )
            return
        have = d["layout"]
        want = options.layout
        if have["hash"] != want.hash:
            raise SchemaError(
                f"{corpus}: the corpus holds layout {have['name']!r} (dim {have['dim']}, hash {have['hash']}); "
                f"this build asks for {want.scene!r} (dim {want.dim}, hash {want.hash})"
            )


def _share_cores(workers: int) -> None:
    """Size a pool worker's thread pools to its share of the cores: pyarrow's CPU pool (the state.csv parse). Decoding,
    cropping and encoding run on the worker's own thread (``marionette.video``); torch and numba are not loaded."""
    import pyarrow as pa

    pa.set_cpu_count(threads_per_worker(workers))


def _ingest_one(args: tuple[SampleRef, str, IngestOptions]) -> SampleResult:
    ref, corpus, options = args
    return ingest_sample(ref, Path(corpus), options, worker=f"pid-{os.getpid()}")


def build_corpus(source: Path, corpus: Path, options: IngestOptions, workers: int = 1, progress: bool = True) -> dict:
    """Discover, ingest every sample (in ``workers`` processes), finalize; returns a build report."""
    corpus = Path(corpus)
    with corpus_lock(corpus, "ingest"):
        check_corpus_options(corpus, options)
        finish_pending(corpus)  # a finalize that crashed completes before anything is re-ingested
        return _build(source, corpus, options, workers, progress)


def check_source(source: Path, refs: list[SampleRef]) -> None:
    """Fail, naming ``source``, when it holds no sample (with a hint when it is itself a sample directory)."""
    if refs:
        return
    source = Path(source)
    hint = ""
    if any((source / f).exists() for f in (STATE_FILE, RGB_FILE, SKELETON_FILE)):
        hint = f": it is a sample directory itself; pass the directory above its part, e.g. {source.parent.parent}"
    elif source.is_dir() and not any(p.is_dir() and p.name.startswith("data_part") for p in source.iterdir()):
        hint = ": it holds no data_part*/ directory (a WildWorld tree is <root>/data_part<x>/<sample>/)"
    raise ValueError(f"{source}: no samples to ingest{hint}")


def _build(source: Path, corpus: Path, options: IngestOptions, workers: int, progress: bool) -> dict:
    skipped: list[tuple[str, str]] = []
    refs = discover(source, skipped)
    check_source(source, refs)
    stage_map = load_stage_map(source)  # read (and checked) before any sample's work
    refs, clashing = check_keys(refs)
    skipped += clashing
    results: list[SampleResult] = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(refs), desc="ingest", unit="sample")
    jobs = [(r, str(corpus), options) for r in refs]
    if workers <= 1:
        for j in jobs:
            results.append(_ingest_one(j))
            if bar:
                bar.update(1)
    else:
        with ProcessPoolExecutor(max_workers=workers, initializer=_share_cores, initargs=(workers,)) as pool:
            for fut in as_completed([pool.submit(_ingest_one, j) for j in jobs]):
                results.append(fut.result())
                if bar:
                    bar.update(1)
    if bar:
        bar.close()
    info = finalize(corpus, options, stage_map)
    results.sort(key=lambda r: r.sample)
    return {"info": info, "results": [r.__dict__ for r in results], "skipped": [[str(p), why] for p, why in skipped]}
