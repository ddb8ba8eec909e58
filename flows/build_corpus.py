"""The ``build-corpus`` flow: WildWorld recordings → a typed corpus, fanned out over Dask.

    discover → ingest every sample (one Prefect task per sample, on Dask workers) → finalize → report

The work lives in ``marionette.ingest``; each task here is one library call. Two flows make one
deployment, ``build-corpus``: the parent picks the Dask cluster from its parameters (a task runner
is fixed when a flow is defined, so the fan-out runs in the subflow ``ingest-samples`` called
through ``with_options(task_runner=...)``), then finalizes and writes the build report.

No rework, twice over: the ingest task's Prefect cache key is the sample's input hash (files +
options), with the cache records kept inside the corpus (``meta/builds/cache/``) so that deleting a
corpus also forgets its cache; and ``ingest_sample`` itself returns "unchanged" without work when
the corpus already holds that input hash.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

from prefect import flow, get_run_logger, task
from prefect.artifacts import create_markdown_artifact
from prefect.cache_policies import NO_CACHE
from prefect.context import TaskRunContext
from prefect.futures import as_completed
from prefect.runtime import flow_run

from flows.fanout import dask_cluster, dask_runner
from marionette import ingest
from marionette.corpus import paths
from marionette.corpus.lock import corpus_lock
from marionette.fanout import worker_identity
from marionette.ingest import IngestOptions, SampleRef, VideoSettings
from marionette.io import printable, write_json


def sample_cache_key(context: TaskRunContext, parameters: dict) -> str | None:
    """Prefect cache key of one sample's ingest: its input hash (file contents + ingest options),
    offered only while the corpus itself holds the sample with that hash — so a corpus whose records
    were removed never has its work skipped by a stale cache entry (None: no caching)."""
    ref, options = parameters["ref"], parameters["options"]
    known = ingest.known_record(Path(parameters["corpus"]), ref)
    if known is None or known.get("retry"):
        return None  # nothing to reuse: no need to hash the files here as well as in ingest_sample
    inputs = ingest.sample_inputs(ref, options, known)  # never reads through a symlink out of the source tree
    if inputs.digests is None:
        return None
    return inputs.hash if known["input_hash"] == inputs.hash else None


# ------------------------------------------------------------------------------------------------
# tasks: one library call each


@task(cache_policy=NO_CACHE)
def check_corpus(corpus: str, options: IngestOptions) -> None:
    """Refuse a corpus of another layout; complete a finalize that crashed before re-ingesting."""
    ingest.check_corpus_options(Path(corpus), options)
    ingest.finish_pending(Path(corpus))


@task(cache_policy=NO_CACHE)
def discover_samples(source: str) -> list[SampleRef]:
    """Every sample under ``source``; an error naming it when there is none. Entries passed over are logged."""
    skipped: list = []
    refs = ingest.discover(Path(source), skipped)
    refs, clashing = ingest.check_keys(refs)
    skipped += clashing
    for path, why in skipped:
        get_run_logger().info("skipped %s", printable(f"{path}: {why}"))
    ingest.check_source(Path(source), refs)
    ingest.load_stage_map(Path(source))  # a tree's stages.json that cannot be read fails the run before any sample's work
    return refs


@task(
    task_run_name="ingest-{ref.part}-{ref.sample_id}",
    cache_key_fn=sample_cache_key,
    result_serializer="json",
    retries=2,
    retry_delay_seconds=5,
)
def ingest_one(ref: SampleRef, corpus: str, options: IngestOptions) -> dict:
    """Ingest one sample; a bad sample is a ``quarantined`` result, not an exception (retries are
    for transient failures such as a worker that vanished)."""
    result = ingest.ingest_sample(ref, Path(corpus), options, worker=worker_identity())
    get_run_logger().info("%s", printable(f"{result.sample}: {result.status} on {result.worker} {result.reason}"))
    return asdict(result)


@task(cache_policy=NO_CACHE)
def finalize_corpus(source: str, corpus: str, options: IngestOptions) -> dict:
    return ingest.finalize(Path(corpus), options, ingest.load_stage_map(Path(source)))


# ------------------------------------------------------------------------------------------------
# flows


@flow(name="ingest-samples")
def ingest_samples(source: str, corpus: str, options: dict) -> list[dict]:
    """Fan ``ingest_one`` out over this flow's task runner; one result per sample, sorted by name.

    A result served from the Prefect cache did no work: it is reported as ``unchanged``, with the
    status the sample had when it was ingested kept as ``previous_status``."""
    logger = get_run_logger()
    opts = IngestOptions.from_json(options)
    refs = discover_samples(source)
    logger.info("%d samples under %s", len(refs), source)
    ingest_task = ingest_one.with_options(
        result_storage=paths.builds_dir(Path(corpus).resolve()) / "cache"
    )  # a Path: local storage
    futures = ingest_task.map(refs, corpus=corpus, options=opts)
    results = []
    for fut in as_completed(futures):
        r = dict(fut.result())
        if fut.state.is_completed() and fut.state.name == "Cached":
            r.update(previous_status=r["status"], status="unchanged", reason="Prefect cache hit: input hash unchanged", worker="")
        results.append(r)
        logger.info(
            "[%d/%d] %s", len(results), len(refs), printable(f"{r['sample']}: {r['status']} {r['worker'] or r['reason']}")
        )
    return sorted(results, key=lambda r: r["sample"])


def build_report(run_id: str, source: str, corpus: str, options: IngestOptions, results: list[dict], info: dict) -> dict:
    counts: dict[str, int] = {}
    for r in results:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    return {
        "flow_run_id": run_id,
        "source": str(source),
        "corpus": str(corpus),
        "options": options.to_json(),
        "counts": counts,
        "workers": sorted({r["worker"] for r in results if r["worker"]}),
        "samples": [
            {k: r.get(k) for k in ("sample", "status", "reason", "worker", "segments", "frames", "input_hash", "previous_status")}
            for r in results
        ],
        "corpus_totals": {k: v for k, v in info.items() if k.startswith("total_")},
    }


def report_markdown(report: dict) -> str:
    lines = [
        f"# build-corpus `{report['corpus']}`",
        "",
        ", ".join(f"{k}: {v}" for k, v in sorted(report["counts"].items())) or "no samples",
        "",
        "corpus: " + ", ".join(f"{k.removeprefix('total_')} {v}" for k, v in report["corpus_totals"].items()),
        "",
        "failures: " + ", ".join(f"{k} {v}" for k, v in report.get("failures", {}).items()),
        "",
        "| sample | status | worker | segments | frames | reason |",
        "|---|---|---|---|---|---|",
    ]
    for s in report["samples"]:
        reason = (s["reason"] or "").replace("|", "\\|").replace("\n", " ")
        lines.append(printable(f"| {s['sample']} | {s['status']} | {s['worker']} | {s['segments']} | {s['frames']} | {reason} |"))
    return "\n".join(lines)


@task(cache_policy=NO_CACHE)
def publish_report(corpus: str, report: dict) -> str:
    """Write ``<corpus>/meta/builds/<flow-run-id>.json`` atomically and publish a markdown artifact."""
    path = paths.builds_dir(corpus) / f"{report['flow_run_id']}.json"
    write_json(path, report)
    create_markdown_artifact(key="build-corpus-report", markdown=report_markdown(report), description=str(path))
    return str(path)


@flow(name="build-corpus")
def build_corpus(
    source: str,
    corpus: str,
    scene: str = "duel",
    rigs: str | None = None,
    monster_species: int | None = None,
    weapon: int | None = None,
    video_height: int = 176,
    video_width: int = 320,
    chunk_frames: int = 81,
    crf: int = 20,
    compression: str = "zstd",
    min_segment_frames: int = 30,
    dask_address: str | None = None,
    n_workers: int = 2,
    scan_terrain: bool = True,
    terrain_frame_stride: int | None = None,
    scan: dict | None = None,
) -> dict:
    """Ingest every WildWorld sample under ``source`` into ``corpus`` and finalize it.

    The fan-out runs on a local Dask cluster of ``n_workers`` processes (one for the whole run: ingest,
    scan and render), or on the existing scheduler
    at ``dask_address`` (its workers must be able to import ``marionette`` and ``flows`` and see both
    paths). After finalize, each stage's terrain is scanned incrementally (the ``rescan-stage``
    subflow, its recordings fanned out on the same cluster, with the corpus's last scan options and ``scan`` /
    ``terrain_frame_stride`` over them) unless ``scan_terrain`` is false. ``rigs`` is a directory of user rigs and
    scenes (``marionette survey --rigs-out``) where ``scene`` is looked up first. Returns the build report, also written to
    ``<corpus>/meta/builds/<flow-run-id>.json``.
    """
    options = IngestOptions(
        scene=scene,
        rigs=rigs,
        monster_species=monster_species,
        weapon=weapon,
        min_segment_frames=min_segment_frames,
        video=VideoSettings(height=video_height, width=video_width, chunk_frames=chunk_frames, crf=crf),
        compression=compression,
    )
    # held by this flow-run process, shared with the writers it calls here; one build per corpus at a time
    with corpus_lock(Path(corpus), "build-corpus flow", share=True), dask_cluster(dask_address, n_workers) as address:
        check_corpus(corpus, options)
        fan_out = ingest_samples.with_options(task_runner=dask_runner(address, n_workers))
        results = fan_out(source, corpus, options.to_json())
        info = finalize_corpus(source, corpus, options)
        terrain = {}
        if scan_terrain and info["total_ingested"]:
            from flows.rescan_stage import rescan_stage

            terrain = rescan_stage(
                corpus,
                incremental=True,
                frame_stride=terrain_frame_stride,
                scan=scan,
                dask_address=address,
                n_workers=n_workers,
            )
        report = build_report(str(flow_run.id), source, corpus, options, results, info)
        report["terrain"] = terrain
        report["failures"] = {
            "quarantined": report["counts"].get("quarantined", 0),
            "terrain": sum(len(r["failed"]) for st, r in terrain.items() if st != "_pose_targets"),
            "depth_mapping": sum(len(r.get("mapping_failed", {})) for st, r in terrain.items() if st != "_pose_targets"),
            "pose": len(terrain.get("_pose_targets", {}).get("failed", {})),
        }
        path = publish_report(corpus, report)
    get_run_logger().info("build report: %s (%s)", path, report["counts"])
    return report
