"""The ``marionette`` command."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def _size(s: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in s.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be HxW, e.g. 176x320, not {s!r}") from None
    return h, w


def cmd_synth(a: argparse.Namespace) -> int:
    from marionette.synth import generate

    t0 = time.time()
    dirs = generate(
        a.out, recordings=a.recordings, seconds=a.seconds, seed=a.seed, width=a.width, height=a.height, workers=a.workers
    )
    print(f"wrote {len(dirs)} recordings under {a.out} in {time.time() - t0:.1f} s")
    return 0


def _options(a: argparse.Namespace):
    from marionette.ingest import IngestOptions, VideoSettings

    h, w = a.video_size
    return IngestOptions(
        scene=a.scene,
        monster_species=a.monster_species,
        weapon=a.weapon,
        min_segment_frames=a.min_segment_frames,
        video=VideoSettings(height=h, width=w, chunk_frames=a.chunk_frames, crf=a.crf),
        compression=a.compression,
    )


def cmd_ingest(a: argparse.Namespace) -> int:
    from marionette.ingest import build_corpus

    t0 = time.time()
    report = build_corpus(a.src, a.corpus, _options(a), workers=a.workers, progress=not a.quiet)
    counts: dict[str, int] = {}
    for r in report["results"]:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
        if r["status"] in ("quarantined", "skipped"):
            print(f"{r['status']}: {r['sample']}: {r['reason']}")
    info = report["info"]
    print(
        f"corpus {a.corpus}: {info['total_segments']} segments, {info['total_frames']} frames, "
        f"{', '.join(f'{v} {k}' for k, v in sorted(counts.items()))} in {time.time() - t0:.1f} s"
    )
    if a.terrain and info["total_ingested"]:
        from terrain_scan.scan import scan_stages

        for st, r in scan_stages(a.corpus, incremental=True, log=lambda *_: None).items():
            print(f"terrain {st}: {len(r['scanned'])} recordings scanned, {len(r['unchanged'])} unchanged, {len(r['chunks_written'])} chunks written")
    if a.pose and info["total_ingested"]:
        _pose_targets(a.corpus)
    return 0


def _pose_targets(corpus: Path) -> None:
    from marionette.bridge.targets import render_pose_targets

    t0 = time.time()
    r = render_pose_targets(corpus)
    print(
        f"pose targets: {len(r.rendered)} of {r.chunks} video chunks rendered ({r.frames_rendered} frames), "
        f"{len(r.shards_rewritten)} video shards rewritten in {time.time() - t0:.1f} s"
    )


def inspect_text(corpus_path: Path) -> str:
    """A human summary of a corpus: segments, frames, hours, splits, vocab, layout, shards, quarantine."""
    from marionette.corpus import Corpus

    c = Corpus(corpus_path)
    info, seg = c.info, c.segments
    lines = [f"corpus   {c.path}"]
    lines.append(f"layout   {c.layout.scene} dim={c.layout.dim} hash={c.layout.hash}")
    for name, (s0, s1) in c.layout.slices.items():
        lines.append(f"           {name:<20} [{s0}, {s1})")
    frames = info["total_frames"]
    lines.append(
        f"samples  {info['total_samples']} ({info['total_ingested']} ingested, {info['total_quarantined']} quarantined, {info['total_skipped']} skipped)"
    )
    lines.append(
        f"segments {info['total_segments']}  frames {frames}  hours {frames / c.fps / 3600:.4f}  fps {c.fps:g}  video chunks {info['total_chunks']}"
    )
    splits: dict[str, list[int]] = {}
    for sp, fr in zip(seg["split"].to_pylist(), seg["frames"].to_pylist()):
        splits.setdefault(sp, [0, 0])
        splits[sp][0] += 1
        splits[sp][1] += fr
    lines.append("splits   " + ", ".join(f"{k}: {v[0]} segments / {v[1]} frames" for k, v in sorted(splits.items())))
    for etype, v in c.vocab["entity_types"].items():
        kinds: dict[str, int] = {}
        for act in v["actions"][1:]:
            kinds[act["class"]] = kinds.get(act["class"], 0) + 1
        lines.append(f"vocab    {etype}: {v['size']} tokens ({', '.join(f'{n} {k}' for k, n in sorted(kinds.items()))})")
    lines.append(f"shards   {len(info['shards'])} state + video: {c.path / 'state'}, {c.path / 'video'}")
    q = c.quarantine.to_pylist()
    lines.append(f"quarantine {len(q)}")
    for r in q:
        lines.append(f"  {r['sample']}: {r['reason']}")
    skipped = [r for r in c.samples.to_pylist() if r["status"] == "skipped"]
    if skipped:
        lines.append(f"skipped  {len(skipped)} (outside the requested slice)")
        for r in skipped:
            lines.append(f"  {r['sample']}: {r['reason']}")
    return "\n".join(lines)


def cmd_inspect(a: argparse.Namespace) -> int:
    if a.json:
        from marionette.corpus import Corpus

        print(json.dumps(Corpus(a.corpus).info, indent=1))
    else:
        print(inspect_text(a.corpus))
    return 0


def cmd_terrain_scan(a: argparse.Namespace) -> int:
    from terrain_scan.depth import DepthDecoder
    from terrain_scan.scan import ScanOptions, scan_stages

    decoder = DepthDecoder.synthetic() if a.depth_decoder is None else DepthDecoder.from_json(json.loads(a.depth_decoder.read_text()))
    options = ScanOptions(decoder=decoder.to_json(), frame_stride=a.frame_stride, voxel_m=a.voxel)
    report = scan_stages(a.corpus, a.stage, incremental=a.incremental, options=options)
    for st, r in report.items():
        print(
            f"stage {st}: {len(r['scanned'])} scanned, {len(r['unchanged'])} unchanged, {len(r['failed'])} failed; "
            f"chunks {len(r['chunks_written'])} written, {len(r['chunks_unchanged'])} unchanged, {len(r['chunks_removed'])} removed; "
            f"{r['layers']} layers ({r['filled']} filled) in {r['dir']}"
        )
    if a.pose:
        _pose_targets(a.corpus)
    return 0


def cmd_terrain_export(a: argparse.Namespace) -> int:
    import numpy as np

    from terrain_scan.mesh import export
    from terrain_scan.scan import stage_dir
    from terrain_scan.store import Stage

    st = Stage(stage_dir(a.corpus, a.stage))
    layers, _ = st.layers()
    if not len(layers):
        raise ValueError(f"{st.dir}: the stage has no terrain yet (run `marionette terrain scan` first)")
    origin = np.array([np.floor(layers.gx.mean()), 0.0, np.floor(layers.gz.mean())])
    export(layers, a.out, origin=origin)
    print(f"wrote {a.out} ({len(layers)} layers; vertices relative to x={origin[0]:g}, z={origin[2]:g})")
    return 0


def cmd_render(a: argparse.Namespace) -> int:
    """Render one corpus segment, or a rollout table, to a G-buffer video."""
    from marionette.bridge.targets import TerrainScene, render_rows, source_size
    from marionette.corpus import Corpus
    from marionette.io import read_ipc
    from marionette.schema import layout_of_schema
    from terrain_scan.scan import stage_dir

    src = Path(a.source)
    t0 = time.time()
    a.camera = a.camera or ("recorded" if src.is_dir() else "follow")
    if src.is_dir():
        if a.segment is None:
            raise ValueError(f"{src}: a corpus needs --segment ID")
        c = Corpus(src)
        rows = c.read_segment(a.segment)
        layout, stage = c.layout, c.segment_row(a.segment)["stage"]
        terrain = TerrainScene.of_stage(a.terrain or stage_dir(src, stage))
        size_src = source_size(c, a.segment) if a.camera == "recorded" else None
    else:
        rows = read_ipc(src)
        layout = layout_of_schema(rows.schema, str(src))
        if a.segment is not None:
            import pyarrow.compute as pc

            rows = rows.filter(pc.equal(rows["segment"], a.segment))
        terrain = TerrainScene.of_stage(a.terrain) if a.terrain else TerrainScene.empty()
        if a.camera == "recorded":
            raise ValueError(f"{src}: a rollout has no recorded camera to follow; use --camera follow")
        size_src = None
    meta = render_rows(layout, rows, a.out, terrain, a.camera, a.size, a.fps, size_src)
    print(f"wrote {a.out}: {meta.width}×{meta.height} at {meta.fps:g} fps, heights {meta.h_min:g}..{meta.h_max:g} m, "
          f"{time.time() - t0:.1f} s")  # fmt: skip
    return 0


def cmd_train_dynamics(a: argparse.Namespace) -> int:
    """Train ActionGPT + PoseGPT on a corpus (resuming from --out when it holds a checkpoint)."""
    from marionette.dynamics.train import run

    run(a)
    return 0


def cmd_train_observation(a: argparse.Namespace) -> int:
    """Train the observation model on a corpus's video shards (resuming from --out)."""
    from marionette.observation.train import ObservationTrainConfig, train, train_in_processes

    keys = ("preset", "steps", "batch_size", "frames", "reduce", "patch", "lr", "warmup", "seed", "checkpoint_every", "control",
            "reference_swap")
    config = ObservationTrainConfig(**{k: getattr(a, k) for k in keys if getattr(a, k) is not None})
    if a.nproc > 1:
        train_in_processes(a.corpus, a.out, config, a.nproc)
    else:
        train(a.corpus, a.out, config)
    return 0


def cmd_generate(a: argparse.Namespace) -> int:
    """Paint RGB onto a pose-control video with a trained observation model."""
    from marionette.observation.generate import main as generate_main

    generate_main(a)
    return 0


def cmd_rollout(a: argparse.Namespace) -> int:
    """Roll a trained dynamics model out from a recorded segment's first frames."""
    from marionette.dynamics.rollout import run

    run(a)
    return 0


def cmd_eval(a: argparse.Namespace) -> int:
    """Run the evaluation protocol on a dynamics checkpoint (and an observation model) and write the report."""
    from marionette.eval.report import evaluate

    s = evaluate(a.dynamics, a.corpus, a.out, observation=a.observation, segments=a.segments, seed_frames=a.seed_frames,
                 horizon=a.horizon, seed=a.seed, fvd_steps=a.fvd_steps, fvd_frames=a.fvd_frames, i3d=a.i3d)  # fmt: skip
    print(f"report: {s['report_md']}")
    return 0


def cmd_demo(a: argparse.Namespace) -> int:
    """Synthetic recordings → corpus → 20 fps view → terrain → pose targets → dynamics → a rollout → observation model →
    evaluation report, end to end."""
    from marionette.corpus import Corpus
    from marionette.eval.report import evaluate
    from marionette.ingest import IngestOptions, build_corpus
    from marionette.synth import generate

    out = Path(a.out)
    src, corpus = out / "recordings", out / "corpus"
    t0 = time.time()
    print(f"[1/9] synthesising {a.recordings} recordings × {a.seconds:g} s into {src}")
    generate(src, recordings=a.recordings, seconds=a.seconds, seed=a.seed, width=a.width, height=a.height, workers=a.workers)
    print(f"[2/9] building the corpus {corpus} with {a.workers} workers")
    build_corpus(src, corpus, IngestOptions(), workers=a.workers, progress=True)
    c = Corpus(corpus)
    rows = sum(c.dynamics_shard(s).num_rows for s in c.shard_ids())
    print(f"[3/9] dynamics view at 20 fps: {rows} rows under {c.dynamics_dir()}")
    from terrain_scan.scan import scan_stages

    for st, r in scan_stages(corpus, incremental=True, log=lambda *_: None).items():
        print(f"[4/9] terrain of stage {st}: {len(r['scanned'])} recordings scanned, {r['layers']} layers in {len(r['chunks_written']) + len(r['chunks_unchanged'])} chunks under {r['dir']}")
    print("[5/9] the bridge: pose-control targets for every video chunk, and one segment seen by the follow camera")
    _pose_targets(corpus)
    seg = c.segment_ids()[0]
    follow = out / f"{seg}-follow.mkv"
    cmd_render(argparse.Namespace(source=corpus, segment=seg, camera="follow", out=follow, size=(352, 640), fps=None, terrain=None))
    print(inspect_text(corpus))
    _demo_dynamics(c, out, a.dynamics_steps)
    _demo_observation(c, out, a.observation_steps)
    print("[9/9] evaluation: state-layer metrics beside the recorded state, controllability probe, rule ablation, proxy-FVD")
    report = evaluate(out / "dynamics", corpus, out / "evaluation", observation=out / "observation", segments=4, seed_frames=32,
                      horizon=80, fvd_steps=8, fvd_frames=41, log=lambda m: print("   ", m))  # fmt: skip
    print(f"    report: {report['report_md']} (plots beside it)")
    print(f"demo finished in {time.time() - t0:.1f} s; corpus at {corpus}")
    return 0


def _demo_dynamics(c, out: Path, steps: int) -> None:
    """The demo's dynamics stages: train the tiny preset, then roll it out with an attack forced and render it."""
    from marionette.dynamics.data import ActionTokens
    from marionette.dynamics.rollout import add_arguments as rollout_arguments
    from marionette.dynamics.rollout import run as run_rollout
    from marionette.dynamics.train import TrainConfig, train

    runs = out / "dynamics"
    t = time.time()
    print(f"[6/9] training ActionGPT + PoseGPT (tiny preset, {steps} steps) into {runs}")
    s = train(c, runs, TrainConfig(preset="tiny", steps=steps, batch_size=8, window=64, lr=2e-3, warmup=50),
              log=lambda m: print("   ", m) if m.startswith(("window", "baselines", "eval")) else None)  # fmt: skip
    print(f"    {s['steps']} steps in {time.time() - t:.1f} s; checkpoint {s['checkpoint']}")
    held = c.segment_ids("test") or c.segment_ids()
    seg = max(held, key=lambda x: c.dynamics_segment(x).num_rows)
    tokens = ActionTokens.from_corpus(c)
    hunter = tokens.entities.index("hunter") if "hunter" in tokens.entities else 0
    entity = tokens.entities[hunter]
    type_key = tokens.type_keys[hunter][1] if tokens.sizes[hunter] > 1 else ""
    classes = {x["composite"]: x.get("class") for x in c.vocab["entity_types"].get(type_key, {}).get("actions", [])}
    attack = next((k for k in range(1, tokens.sizes[hunter]) if classes.get(int(tokens.composites[hunter][k])) == "attack"), None)
    states, video = out / f"{seg}-rollout.arrow", out / f"{seg}-rollout.mkv"
    argv = [str(runs), str(c.path), "--segment", seg, "--seed-frames", "32", "--horizon", "200", "--out", str(states),
            "--render", str(video), "--size", "352x640"]  # fmt: skip
    if attack is not None:
        argv += ["--force", f"{entity}:40:60:{attack}"]
    print(f"[7/9] rollout of {seg}: 32 seed frames, 200 predicted (10 s), {entity} forced to attack over frames 40–59, rules on")
    ap = argparse.ArgumentParser()
    rollout_arguments(ap)
    run_rollout(ap.parse_args(argv), log=lambda m: print("   ", m))


def _demo_observation(c, out: Path, steps: int) -> None:
    """The demo's observation stage: train the tiny video model, then paint a held-out chunk's pose video from its first frame."""
    import tarfile

    from marionette.ingest.video import decode_frames
    from marionette.observation.generate import main as generate_main
    from marionette.observation.generate import write_image
    from marionette.observation.train import ObservationTrainConfig, train

    runs = out / "observation"
    t = time.time()
    video = c.info["ingest"]["video"]
    reduce = 8 if video["height"] % 8 == 0 and video["width"] % 8 == 0 else 4
    print(f"[8/9] training the observation model (tiny video DiT, {steps} steps, 1/{reduce} of the chunk size) into {runs}")
    s = train(c, runs, ObservationTrainConfig(preset="tiny", steps=steps, batch_size=4, frames=5, reduce=reduce, patch=2, lr=1e-3,
                                              warmup=20), log=lambda m: print("   ", m))  # fmt: skip
    print(f"    {s['steps']} steps in {time.time() - t:.1f} s")
    held = set(c.segment_ids("test") or c.segment_ids())
    for shard in sorted((c.path / "video").glob("shard-*.tar")):
        with tarfile.open(shard) as tar:
            keys = [n[: -len(".pose.mkv")] for n in tar.getnames() if n.endswith(".pose.mkv") and n.split("__c")[0] in held]
            if keys:
                (out / "pose.mkv").write_bytes(tar.extractfile(f"{keys[0]}.pose.mkv").read())
                first = decode_frames(tar.extractfile(f"{keys[0]}.rgb.mp4").read())[0]
                break
    else:
        print("    no held-out chunk with a pose target: nothing to generate")
        return
    write_image(out / "first.png", first)
    generate_main(argparse.Namespace(ckpt=runs, pose=out / "pose.mkv", first_frame=out / "first.png", out=out / "generated.mp4",
                                     chunks=4, steps=8, seed=0, fps=30.0))  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="marionette", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)

    s = sub.add_parser("synth", help="write synthetic WildWorld-format recordings")
    s.add_argument("out", type=Path)
    s.add_argument("--recordings", type=int, default=2)
    s.add_argument("--seconds", type=float, default=20.0)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--width", type=int, default=320)
    s.add_argument("--height", type=int, default=180)
    s.add_argument("--workers", type=int, default=1, help="recordings generated in parallel processes")
    s.set_defaults(fn=cmd_synth)

    s = sub.add_parser("ingest", help="ingest WildWorld recordings into a corpus (then finalize)")
    s.add_argument("src", type=Path)
    s.add_argument("corpus", type=Path)
    s.add_argument("--scene", default="duel")
    s.add_argument("--monster-species", type=int, default=None)
    s.add_argument("--weapon", type=int, default=None)
    s.add_argument("--workers", type=int, default=1)
    s.add_argument("--min-segment-frames", type=int, default=30)
    s.add_argument("--video-size", type=_size, default=(176, 320), help="training resolution HxW")
    s.add_argument("--chunk-frames", type=int, default=81)
    s.add_argument("--crf", type=int, default=20, help="x264 quality of the video chunks (lower is better)")
    s.add_argument("--compression", choices=["none", "lz4", "zstd"], default="zstd")
    s.add_argument("--quiet", action="store_true")
    s.add_argument("--no-terrain", dest="terrain", action="store_false", help="skip the incremental terrain scan after ingest")
    s.add_argument("--no-pose", dest="pose", action="store_false", help="skip rendering the pose-control targets after ingest")
    s.set_defaults(fn=cmd_ingest)

    s = sub.add_parser("inspect", help="summarise a corpus")
    s.add_argument("corpus", type=Path)
    s.add_argument("--json", action="store_true", help="print info.json")
    s.set_defaults(fn=cmd_inspect)

    t = sub.add_parser("terrain", help="terrain scans: scan a corpus's stages, export meshes")
    tsub = t.add_subparsers(dest="terrain_cmd", required=True)
    s = tsub.add_parser("scan", help="scan the stages of a corpus into layered height-field chunks")
    s.add_argument("corpus", type=Path)
    s.add_argument("--stage", default=None, help="one stage id (default: every stage)")
    s.add_argument("--incremental", action="store_true", help="scan only recordings that are new or changed")
    s.add_argument("--frame-stride", type=int, default=1, help="use every Nth depth frame")
    s.add_argument("--voxel", type=float, default=0.25, help="voxel size of the point down-sampling, metres")
    s.add_argument("--depth-decoder", type=Path, default=None, help="JSON of the 8-bit depth mapping (default: the synthetic game's)")
    s.add_argument("--no-pose", dest="pose", action="store_false", help="do not bring the pose-control targets up to date")
    s.set_defaults(fn=cmd_terrain_scan)
    s = tsub.add_parser("export", help="export a stage's terrain as a PLY or GLB mesh")
    s.add_argument("corpus", type=Path)
    s.add_argument("--stage", default="default")
    s.add_argument("--out", type=Path, required=True)
    s.set_defaults(fn=cmd_terrain_export)

    s = sub.add_parser("render", help="render a corpus segment or a rollout table to a lossless G-buffer video")
    s.add_argument("source", type=Path, help="a corpus directory or a STATES.arrow rollout")
    s.add_argument("--segment", default=None, help="segment id (required for a corpus)")
    s.add_argument("--camera", choices=["recorded", "follow"], default=None, help="default: recorded for a corpus, follow for a rollout")
    s.add_argument("--out", type=Path, required=True, help="output .mkv")
    s.add_argument("--size", type=_size, default=(704, 1280), help="HxW (default 704x1280)")
    s.add_argument("--fps", type=float, default=None, help="output rate (default: the state's)")
    s.add_argument("--terrain", type=Path, default=None, help="a stage directory (default: the segment's stage)")
    s.set_defaults(fn=cmd_render)

    t = sub.add_parser("train", help="train a model on a corpus")
    tsub = t.add_subparsers(dest="train_cmd", required=True)
    s = tsub.add_parser("dynamics", help="train ActionGPT + PoseGPT (a rerun with the same --out resumes)")
    from marionette.dynamics.train import add_arguments as train_arguments

    train_arguments(s)
    s.set_defaults(fn=cmd_train_dynamics)

    s = tsub.add_parser("observation", help="train the observation model (pose video + first frame → RGB) on the video shards")
    s.add_argument("corpus", type=Path)
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--preset", default=None, help="tiny (default) or small")
    s.add_argument("--control", choices=["pose", "actions"], default=None,
                   help="pose (default): pose-control video; actions: the pixel-AR baseline (first frame + action schedule)")  # fmt: skip
    for flag, kind in (("--steps", int), ("--batch-size", int), ("--frames", int), ("--reduce", int), ("--patch", int),
                       ("--lr", float), ("--warmup", int), ("--seed", int), ("--checkpoint-every", int)):  # fmt: skip
        s.add_argument(flag, type=kind, default=None)
    s.add_argument("--reference-swap", type=float, default=None,
                   help="probability that a training clip's first frame comes from another chunk (pose control; teaches pose-following)")  # fmt: skip
    s.add_argument("--nproc", type=int, default=1, help="processes: > 1 trains under torchrun (DDP)")
    s.set_defaults(fn=cmd_train_observation)

    s = sub.add_parser("generate", help="paint RGB onto a pose-control video with a trained observation model")
    from marionette.observation.generate import add_arguments as generate_arguments

    generate_arguments(s)
    s.set_defaults(fn=cmd_generate)

    s = sub.add_parser("rollout", help="roll a trained dynamics model out from a recorded segment, with forced tokens and scripted roots")
    from marionette.dynamics.rollout import add_arguments as rollout_arguments

    rollout_arguments(s)
    s.set_defaults(fn=cmd_rollout)

    s = sub.add_parser("eval", help="evaluate a dynamics checkpoint: state metrics, controllability probe, rule ablation, proxy-FVD")
    s.add_argument("dynamics", type=Path, help="a dynamics checkpoint or training directory")
    s.add_argument("corpus", type=Path)
    s.add_argument("--out", type=Path, required=True, help="the report directory")
    s.add_argument("--observation", type=Path, default=None, help="an observation checkpoint or training directory (for the video rows)")
    s.add_argument("--segments", type=int, default=8, help="held-out windows")
    s.add_argument("--seed-frames", type=int, default=64, help="recorded context frames of each window")
    s.add_argument("--horizon", type=int, default=120, help="predicted frames of each window")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--fvd-steps", type=int, default=20, help="sampling steps of the observation model for proxy-FVD")
    s.add_argument("--fvd-frames", type=int, default=None, help="at most this many video frames per proxy-FVD clip (default: whole)")
    s.add_argument("--i3d", type=Path, default=None, help="Inception-I3D weights (safetensors) for FVD proper (default: the labelled proxy)")
    s.set_defaults(fn=cmd_eval)

    s = sub.add_parser("demo", help="run the pipeline end to end on synthetic data")
    s.add_argument("--out", type=Path, default=Path("demo-run"))
    s.add_argument("--recordings", type=int, default=4)
    s.add_argument("--seconds", type=float, default=20.0)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--width", type=int, default=320)
    s.add_argument("--height", type=int, default=180)
    s.add_argument("--workers", type=int, default=2)
    s.add_argument("--dynamics-steps", type=int, default=1000, help="training steps of the demo's tiny dynamics model")
    s.add_argument("--observation-steps", type=int, default=1000, help="training steps of the demo's tiny observation model")
    s.set_defaults(fn=cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.fn(args)
    except (FileNotFoundError, ValueError, RuntimeError, KeyError) as exc:
        print(f"marionette {args.cmd}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
