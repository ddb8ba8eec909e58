"""Finalize: move staged samples into numbered shards and derive the corpus metadata.

The move is planned first (``meta/finalize-plan.json``, written atomically), then carried out with
renames that are safe to repeat, so a crash at any point is repaired by running finalize again.
Derived files — segments, quarantine, vocab, stats, info — are recomputed from the per-sample
records in ``meta/samples/``, whose size grows with the number of recordings, not of frames.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa

from marionette.corpus import MODEL_FPS, paths
from marionette.corpus.info import POSE_PATH, STATE_PATH, VIDEO_PATH, CorpusInfo
from marionette.corpus.stages import UNPLACED, read_placements
from marionette.corpus.vocab import classify
from marionette.ingest.sample import INGEST_VERSION, IngestOptions, merge_action_stats, merge_moments
from marionette.io import read_json, text_sha256, write_json, write_parquet
from marionette.schema import layout_from_json


def build_vocab(records: list[dict]) -> dict:
    """Dense tokens per entity type over the corpus (token 0 = no valid action), clip lengths, kinds, classes."""
    by_str: dict[str, dict[str, dict]] = {}
    for r in records:
        merge_action_stats(by_str, r.get("actions", {}))
    merged = {etype: {int(cid): d for cid, d in acts.items()} for etype, acts in by_str.items()}
    vocab: dict = {"version": 1, "entity_types": {}}
    for etype in sorted(merged):
        actions = [
            {
                "composite": 0,
                "token": 0,
                "name": "no valid action",
                "clip_length": 1,
                "kind": "none",
                "class": "none",
                "frames": 0,
            }
        ]
        token = 1
        for cid in sorted(merged[etype]):
            d = merged[etype][cid]
            if cid == 0:
                actions[0]["frames"] = d["frames"]
                continue
            kind = "state" if d["wraps"] else "event"
            inst = np.asarray(d["instances"], np.float64).reshape(-1, 3)
            actions.append(
                {
                    "composite": cid,
                    "bank": (cid - 1) // 1000,
                    "motion": (cid - 1) % 1000,
                    "token": token,
                    "clip_length": d["max_motion_frame"] + 1,
                    "kind": kind,
                    "class": classify(kind, d["instances"]),
                    "frames": d["frames"],
                    "instances": len(inst),
                    "median_root_speed_mps": round(float(np.median(inst[:, 0])), 4) if len(inst) else 0.0,
                    "median_peak_body_speed_mps": round(float(np.median(inst[:, 1])), 4) if len(inst) else 0.0,
                }
            )
            token += 1
        vocab["entity_types"][etype] = {"size": token, "actions": actions}
    vocab["hash"] = text_sha256(json.dumps(vocab["entity_types"], sort_keys=True))[:16]
    return vocab


def build_stats(records: list[dict]) -> dict:
    """Per-feature mean/std/min/max over the train split (all samples if it is empty)."""
    train = [r for r in records if r.get("split") == "train"] or records
    acc: dict[str, dict] = {}
    for r in train:
        for k, m in (r.get("stats") or {}).items():
            acc[k] = merge_moments(acc.get(k), m)
    out = {"split": "train" if any(r.get("split") == "train" for r in records) else "all"}
    for k, m in sorted(acc.items()):
        n = max(m["count"], 1)
        out[k] = {
            "mean": m["mean"],
            "std": np.sqrt(np.asarray(m["m2"]) / n).tolist(),
            "min": m["min"],
            "max": m["max"],
            "count": m["count"],
        }
    return out


def _read_record(p: Path) -> dict:
    """A sample record (committed or staged), checked to be a JSON object whose key is its file's own name."""
    try:
        rec = read_json(p)
    except ValueError as exc:
        raise ValueError(f"not a sample record: {exc}") from None
    own = p.stem if p.name != "record.json" else p.parent.name
    if not isinstance(rec, dict) or rec.get("key") != own:
        raise paths.CorpusPathError(f"{p}: record key {rec.get('key') if isinstance(rec, dict) else rec!r} is not {own!r}")
    paths.check_id(own, "sample key", str(p))
    for field in ("shard", "retired_shard"):
        if rec.get(field) is not None:
            paths.check_shard(rec[field], f"{p}: {field}")
    return rec


def _load_records(d: Path) -> list[dict]:
    return [_read_record(p) for p in sorted(d.glob("*.json"))] if d.exists() else []


def _plan(corpus: Path, options_key: str | None) -> dict:
    """Shard numbers and renames for every staged record; paths relative to the corpus."""
    committed = {r["key"]: r for r in _load_records(paths.samples_dir(corpus))}
    staged = []
    for p in sorted(paths.staging_root(corpus).glob("*/record.json")):
        rec = _read_record(p)
        if options_key is not None and rec.get("options_key") != options_key:
            shutil.rmtree(p.parent, ignore_errors=True)  # staged by a build with other options: stale
            continue
        staged.append(rec)
    staged.sort(key=lambda r: r["sample"])
    # a shard number is never given to another recording, even after its own was retired
    used = [n for r in committed.values() for n in (r.get("shard"), r.get("retired_shard")) if n is not None]
    next_shard = max(used) + 1 if used else 0
    moves, deletes, records, drops = [], [], [], []
    keys_of: dict[str, list[str]] = {}
    for key, r in committed.items():
        keys_of.setdefault(r.get("sample"), []).append(key)
    for rec in staged:
        # the same recording committed under another key (a key made by another version's naming): it goes, its
        # shard with it, so a recording is never held twice
        for key in keys_of.get(rec["sample"], []):
            if key != rec["key"]:
                drops.append(key)
                if committed[key].get("shard") is not None:
                    name = paths.shard_name(committed[key]["shard"])
                    deletes += [f"state/{name}.arrow", f"video/{name}.tar"]
        old = committed.get(rec["key"]) or {}
        own = old.get("shard") if old.get("shard") is not None else old.get("retired_shard")
        stage = f"staging/{rec['key']}"
        if rec["status"] == "ingested":
            if own is None:
                own, next_shard = next_shard, next_shard + 1
            rec["shard"] = own
            moves.append([f"{stage}/state.arrow", f"state/{paths.shard_name(own)}.arrow", rec["input_hash"]])
            moves.append([f"{stage}/video.tar", f"video/{paths.shard_name(own)}.tar", rec["input_hash"]])
        else:
            rec["shard"] = None
            if own is not None:  # a recording that was good and now is not: its shard goes, its number stays reserved
                rec["retired_shard"] = own
                deletes += [f"state/{paths.shard_name(own)}.arrow", f"video/{paths.shard_name(own)}.tar"]
        records.append(rec)
    return {"records": records, "moves": moves, "deletes": deletes, "drops": drops}


def _checked_plan(corpus: Path, plan: object, where: str) -> tuple[list, list, list, list]:
    """(moves, deletes, records, drops) of a plan, every entry checked to name a path of this corpus: a plan is
    read back from disk, so nothing in it is trusted, and nothing is touched unless all of it is valid."""
    if not isinstance(plan, dict) or not all(isinstance(plan.get(k), list) for k in ("moves", "deletes", "records")):
        raise ValueError(f"{where}: not a finalize plan (moves, deletes, records)")
    moves = []
    for i, entry in enumerate(plan["moves"]):
        if not (isinstance(entry, list) and len(entry) == 3 and isinstance(entry[2], str)):
            raise ValueError(f"{where}: moves[{i}] is not [source, destination, input hash]")
        src = paths.resolve_plan_entry(corpus, entry[0], f"{where}: moves[{i}]")
        dst = paths.resolve_plan_entry(corpus, entry[1], f"{where}: moves[{i}]")
        if not entry[0].startswith("staging/") or entry[1].startswith("staging/"):
            raise paths.CorpusPathError(f"{where}: moves[{i}] {entry[:2]} does not move a staged file into a shard")
        moves.append((src, dst, entry[2]))
    deletes = []
    for i, rel in enumerate(plan["deletes"]):
        if isinstance(rel, str) and rel.startswith("staging/"):
            raise paths.CorpusPathError(f"{where}: deletes[{i}] {rel!r} is not a shard")
        deletes.append(paths.resolve_plan_entry(corpus, rel, f"{where}: deletes[{i}]"))
    records = []
    for i, rec in enumerate(plan["records"]):
        if not isinstance(rec, dict):
            raise ValueError(f"{where}: records[{i}] is not a sample record")
        paths.check_id(rec.get("key"), "sample key", f"{where}: records[{i}]")
        records.append(rec)
    if not isinstance(plan.get("drops", []), list):
        raise ValueError(f"{where}: drops is not a list of sample keys")
    drops = [paths.sample_record(corpus, k, f"{where}: drops") for k in plan.get("drops", [])]
    return moves, deletes, records, drops


def _execute(corpus: Path, plan: dict, where: str) -> None:
    """Carry out a plan; every step is safe to repeat after a crash."""
    moves, deletes, records, drops = _checked_plan(corpus, plan, where)
    for src_p, dst_p, h in moves:
        if src_p.exists():
            staged = src_p.parent / "record.json"
            if staged.exists() and read_json(staged)["input_hash"] != h:
                raise RuntimeError(f"{staged}: staged sample changed after {where} was written")
            os.replace(src_p, dst_p)
        elif not dst_p.exists():
            raise FileNotFoundError(f"finalize: staged file {src_p} is gone and {dst_p} does not exist")
    for p in deletes:
        p.unlink(missing_ok=True)
    for rec in records:
        write_json(paths.sample_record(corpus, rec["key"]), rec)
        shutil.rmtree(paths.staging_dir(corpus, rec["key"]), ignore_errors=True)
    for p in drops:
        p.unlink(missing_ok=True)


def finish_pending(corpus: Path) -> bool:
    """Complete a finalize that crashed after writing its plan; True if there was one."""
    plan_path = paths.meta(corpus, "finalize-plan.json")
    if not plan_path.exists():
        return False
    try:
        plan = read_json(plan_path)
    except ValueError as exc:
        raise ValueError(f"not a finalize plan: {exc}") from None
    _execute(Path(corpus), plan, str(plan_path))
    plan_path.unlink()
    return True


def finalize(corpus: Path, options: IngestOptions | None = None, stages: dict[str, str] | None = None) -> dict:
    """Commit staged samples to numbered shards and rewrite the derived metadata; returns info.json.

    Staged samples from a build with other ingest options are discarded, not committed.
    """
    corpus = Path(corpus)
    paths.state_dir(corpus).mkdir(parents=True, exist_ok=True)
    paths.video_dir(corpus).mkdir(parents=True, exist_ok=True)
    plan_path = paths.meta(corpus, "finalize-plan.json")
    finish_pending(corpus)
    plan = _plan(corpus, options.key() if options is not None else None)
    if plan["records"]:
        write_json(plan_path, plan)
        _execute(corpus, plan, str(plan_path))
        plan_path.unlink()
    return write_metadata(corpus, options, stages)


SEGMENT_COLUMNS = (
    "segment",
    "sample",
    "stage",
    "scene",
    "species",
    "weapon",
    "frames",
    "start",
    "stop",
    "chunks",
    "split",
    "shard",
    "hash",
)
SEGMENT_INT_COLUMNS = ("species", "weapon", "frames", "start", "stop", "chunks", "shard")


def write_metadata(corpus: Path, options: IngestOptions | None = None, stages: dict[str, str] | None = None) -> dict:
    """Derive segments.parquet, samples.parquet, quarantine.parquet, vocab.json, stats.json and info.json."""
    info_path = paths.meta(corpus, paths.INFO)
    old_info = CorpusInfo.read(info_path) if info_path.exists() else None
    if options is None:
        if old_info is None:
            raise FileNotFoundError(f"{info_path}: no corpus here and no ingest options given")
        options = IngestOptions.from_json(old_info.ingest)
    stages = dict(stages or {})
    if old_info:
        stages = {**old_info.stages, **stages}
    placed = read_placements(corpus)  # the terrain scan's grouping (or a user's edit of it); the source's map wins
    records = _load_records(paths.samples_dir(corpus))
    ingested = [r for r in records if r["status"] == "ingested"]
    layouts = _layouts(options, ingested)

    seg_rows = _segment_rows(ingested, layouts, stages, placed)
    write_parquet(
        paths.meta(corpus, paths.SEGMENTS),
        pa.table({k: pa.array(v, pa.int32() if k in SEGMENT_INT_COLUMNS else pa.string()) for k, v in seg_rows.items()}),
    )
    bad = [r for r in records if r["status"] == "quarantined"]
    write_parquet(paths.meta(corpus, paths.SAMPLES), _samples_table(records))
    write_parquet(paths.meta(corpus, paths.QUARANTINE), _quarantine_table(bad))
    vocab, stats = _vocab_and_stats(ingested, layouts)
    write_json(paths.meta(corpus, paths.VOCAB), vocab)
    write_json(paths.meta(corpus, paths.STATS), stats)
    info = _info(options, layouts, records, ingested, bad, seg_rows, stages, vocab)
    write_json(info_path, CorpusInfo.from_json(info, str(info_path)).to_json())
    return info


def _segment_rows(ingested: list[dict], layouts: dict, stages: dict[str, str], placed: dict[str, str]) -> dict[str, list]:
    """The columns of segments.parquet: one row per segment of every ingested sample, with its sample's stage (the
    source's map, else the scan's placement), scene, species and weapon."""
    seg_rows: dict[str, list] = {k: [] for k in SEGMENT_COLUMNS}
    for r in ingested:
        layout = layouts[r.get("scene", next(iter(layouts)))]
        types = r.get("types", {})
        species = next((types[e.name] for e in layout.entities if e.source_kind == "m"), -1)
        weapon = next((types[e.name] for e in layout.entities if e.source_kind == "w"), -1)
        for s in r["segments"]:
            for k, v in (
                ("segment", s["segment"]),
                ("sample", r["sample"]),
                ("stage", stages.get(r["sample"], placed.get(r["sample"], UNPLACED))),
                ("scene", layout.scene),
                ("species", species),
                ("weapon", weapon),
                ("frames", s["frames"]),
                ("start", s["start"]),
                ("stop", s["stop"]),
                ("chunks", s.get("chunks", 0)),
                ("split", s["split"]),
                ("shard", r["shard"]),
                ("hash", s["hash"]),
            ):
                seg_rows[k].append(v)
    return seg_rows


def _samples_table(records: list[dict]) -> pa.Table:
    """samples.parquet: every sample's status, reason, input hash, shard, source and state hash."""
    return pa.table(
        {
            "sample": pa.array([r["sample"] for r in records], pa.string()),
            "status": pa.array([r["status"] for r in records], pa.string()),
            "reason": pa.array([r.get("reason", "") for r in records], pa.string()),
            "input_hash": pa.array([r["input_hash"] for r in records], pa.string()),
            "shard": pa.array([r.get("shard") for r in records], pa.int32()),
            "source": pa.array([r.get("source", "") for r in records], pa.string()),
            "state_hash": pa.array([r.get("state_hash", "") for r in records], pa.string()),
        }
    )


def _quarantine_table(bad: list[dict]) -> pa.Table:
    """quarantine.parquet: each quarantined sample with its reason."""
    return pa.table(
        {
            "sample": pa.array([r["sample"] for r in bad], pa.string()),
            "reason": pa.array([r["reason"] for r in bad], pa.string()),
            "input_hash": pa.array([r["input_hash"] for r in bad], pa.string()),
            "source": pa.array([r.get("source", "") for r in bad], pa.string()),
        }
    )


def _vocab_and_stats(ingested: list[dict], layouts: dict) -> tuple[dict, dict]:
    """vocab.json and stats.json: one of each, or one per scene where scenes differ (a species' actions and body are
    its own)."""
    if len(layouts) > 1:
        scenes = {name: [r for r in ingested if r.get("scene") == name] for name in layouts}
        per = {name: build_vocab(recs) for name, recs in scenes.items()}
        vocab = {"version": 1, "scenes": per, "hash": text_sha256(json.dumps({n: v["hash"] for n, v in per.items()}))[:16]}
        return vocab, {"scenes": {name: build_stats(recs) for name, recs in scenes.items()}}
    return build_vocab(ingested), build_stats(ingested)


def _info(
    options: IngestOptions,
    layouts: dict,
    records: list[dict],
    ingested: list[dict],
    bad: list[dict],
    seg_rows: dict[str, list],
    stages: dict[str, str],
    vocab: dict,
) -> dict:
    """info.json's fields (``CorpusInfo`` checks them): the layouts, rates, ingest options, totals and path templates."""
    only = next(iter(layouts.values())) if len(layouts) == 1 else None
    fps = sorted({r["fps"] for r in ingested}) or [30.0]
    splits: dict[str, int] = {}
    for r in ingested:
        for s in r["segments"]:
            splits[s["split"]] = splits.get(s["split"], 0) + s["frames"]
    return {
        "codebase_version": f"marionette-ingest-{INGEST_VERSION}",
        "layout": {"hash": only.hash, **only.to_json()} if only is not None else {},
        **({"layouts": {n: {"hash": x.hash, **x.to_json()} for n, x in layouts.items()}} if len(layouts) > 1 else {}),
        "fps": fps[0] if len(fps) == 1 else fps,
        "dynamics_fps": int(MODEL_FPS),
        "ingest": options.to_json(),
        "features": features(only) if only is not None else {n: features(x) for n, x in layouts.items()},
        "total_samples": len(records),
        "total_ingested": len(ingested),
        "total_quarantined": len(bad),
        "total_skipped": sum(r["status"] == "skipped" for r in records),
        "total_segments": len(seg_rows["segment"]),
        "total_frames": int(sum(seg_rows["frames"])),
        "total_chunks": int(sum(seg_rows["chunks"])),
        "frames_per_split": splits,
        "shards": sorted(r["shard"] for r in ingested),
        "stages": stages,
        "vocab_hash": vocab["hash"],
        "state_path": STATE_PATH,
        "video_path": VIDEO_PATH,
        "pose_path": POSE_PATH,
    }


def _layouts(options: IngestOptions, ingested: list[dict]) -> dict:
    """Scene → layout of what the corpus holds: the options' scene, or with ``auto`` each ingested recording's own
    (carried in its record), in name order."""
    if not options.auto:
        return {options.layout.scene: options.layout}
    out = {}
    for r in sorted(ingested, key=lambda r: r["sample"]):
        d = r.get("layout")
        if not isinstance(d, dict) or r.get("scene") != d.get("name"):
            raise ValueError(f"{r['sample']}: its record carries no layout of scene {r.get('scene')!r}")
        got = layout_from_json({k: v for k, v in d.items() if k != "hash"})
        if got.scene in out and out[got.scene].hash != got.hash:
            raise ValueError(f"{r['sample']}: scene {got.scene!r} with another layout than the corpus's (a rig changed?)")
        out[got.scene] = got
    return dict(sorted(out.items()))


def features(layout) -> dict:
    """LeRobot-style features: every column of a state shard with dtype, shape and names."""
    f = {
        "segment": {"dtype": "string", "shape": [1], "names": None},
        "sample": {"dtype": "string", "shape": [1], "names": None},
        "frame": {"dtype": "int32", "shape": [1], "names": None},
        "t": {"dtype": "float64", "shape": [1], "names": None},
        "state": {"dtype": "float32", "shape": [layout.dim], "names": layout.dim_names()},
    }
    for e in layout.articulated:
        f[f"{e.name}.type_id"] = {"dtype": "int32", "shape": [1], "names": None}
        f[f"{e.name}.action"] = {"dtype": "int32", "shape": [1], "names": None}
        f[f"{e.name}.motion_frame"] = {"dtype": "int32", "shape": [1], "names": None}
        f[f"{e.name}.hp"] = {"dtype": "float32", "shape": [1], "names": None}
        f[f"{e.name}.root_world"] = {"dtype": "float64", "shape": [3], "names": ["x", "y", "z"]}
        f[f"{e.name}.rot_world"] = {"dtype": "float64", "shape": [4], "names": ["x", "y", "z", "w"]}
        f[f"{e.name}.pos_check_m"] = {"dtype": "float32", "shape": [1], "names": None}
    for e in layout.attachments:
        f[f"{e.name}.type_id"] = {"dtype": "int32", "shape": [1], "names": None}
    f["camera.K"] = {"dtype": "float64", "shape": [4], "names": ["fx", "fy", "cx", "cy"]}
    f["camera.pos"] = {"dtype": "float64", "shape": [3], "names": ["x", "y", "z"]}
    f["camera.rot"] = {"dtype": "float64", "shape": [4], "names": ["x", "y", "z", "w"]}
    f["valid"] = {"dtype": "bool", "shape": [1], "names": None}
    return f
