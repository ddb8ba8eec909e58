"""The ``marionette`` command as a person meets it: options checked as they are parsed, every default in
--help, segment ids listed and near ones suggested, a chunk taken out for ``generate``, errors as one line."""

from __future__ import annotations

import argparse
import json
import shutil

import numpy as np
import pyarrow as pa
import pytest

from marionette.bridge.gbuffer import decode_gbuffer
from marionette.bridge.targets import render_pose_targets
from marionette.cli import build_parser, error_message, main
from marionette.corpus import Corpus
from marionette.corpus.paths import chunk_key
from marionette.corpus.video_shards import read_joined
from marionette.observation.generate import load_inputs, read_image
from marionette.video import decode_frames


@pytest.fixture(scope="module")
def posed(corpus, tmp_path_factory):
    """A copy of the session corpus with every video chunk's pose target rendered."""
    out = tmp_path_factory.mktemp("cli-posed") / "corpus"
    shutil.copytree(corpus, out)
    render_pose_targets(out)
    return out


@pytest.fixture(scope="module")
def unposed(posed, tmp_path_factory):
    """A copy of ``posed`` without its pose shards (as before any target was rendered)."""
    out = tmp_path_factory.mktemp("cli-unposed") / "corpus"
    shutil.copytree(posed, out)
    shutil.rmtree(out / "pose")
    return out


def chunked_segment(corpus) -> str:
    """A segment with at least one video chunk."""
    rows = Corpus(corpus).segments.to_pylist()
    return next(r["segment"] for r in rows if r["chunks"] > 0)


def parse_error(argv, capsys) -> str:
    """The parser's exit: status 2 and its message."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    return capsys.readouterr().err


BAD_OPTIONS = [  # (command line, the flag named, why), SRC an empty directory and OUT a path that must stay absent
    ("ingest SRC OUT --video-size 0x0", "--video-size", "greater than 0"),
    ("ingest SRC OUT --video-size 71x128", "--video-size", "even"),
    ("ingest SRC OUT --chunk-frames 0", "--chunk-frames", "4k + 1"),
    ("ingest SRC OUT --chunk-frames 80", "--chunk-frames", "4k + 1"),
    ("ingest SRC OUT --crf 99", "--crf", "0 to 51"),
    ("ingest SRC OUT --min-segment-frames -5", "--min-segment-frames", "at least 1"),
    ("ingest SRC OUT --workers 0", "--workers", "at least 1"),
    ("ingest SRC OUT --scene duell", "--scene", "did you mean duel"),
    ("render SRC --segment x --size 0x0 --out OUT/x.mkv", "--size", "greater than 0"),
    ("render SRC --segment x --fps 0 --out OUT/x.mkv", "--fps", "greater than 0"),
    ("render SRC --segment x --out OUT/x.mp4", "--out", "ends in .mkv"),
    ("synth OUT --seconds 0", "--seconds", "greater than 0"),
    ("synth OUT --recordings 0", "--recordings", "at least 1"),
    ("synth OUT --width 321", "--width", "even"),
    ("terrain scan SRC --voxel 0", "--voxel", "greater than 0"),
    ("terrain scan SRC --frame-stride 0", "--frame-stride", "at least 1"),
    ("terrain export SRC --out OUT/stage.obj", "--out", ".ply or .glb"),
    ("rollout SRC SRC --segment x --horizon 0 --out OUT/s.arrow", "--horizon", "at least 1"),
    ("rollout SRC SRC --segment x --horizon 9 --force hunter:5:2:1 --out OUT/s.arrow", "--force", "empty or negative"),
    ("rollout SRC SRC --segment x --horizon 9 --rules colider --out OUT/s.arrow", "--rules", "collider,cap"),
    ("rollout SRC SRC --segment x --horizon 9 --temperature -1 --out OUT/s.arrow", "--temperature", "at least 0"),
    ("generate SRC --pose p.mkv --first-frame f.png --out OUT/g.mp4 --steps 0", "--steps", "at least 1"),
    ("eval SRC SRC --out OUT/r --segments 0", "--segments", "at least 1"),
    ("eval SRC SRC --out OUT/r --horizon x", "--horizon", "an integer"),
    ("demo --out OUT/d --dynamics-steps 0", "--dynamics-steps", "at least 1"),
    ("export-chunk SRC --segment x --chunk -1 --out OUT/c", "--chunk", "at least 0"),
]


@pytest.mark.parametrize("line, flag, why", BAD_OPTIONS)
def test_a_bad_option_exits_2_before_any_work(line, flag, why, tmp_path, capsys):
    (tmp_path / "src").mkdir()
    out = tmp_path / "out"
    err = parse_error([a.replace("SRC", str(tmp_path / "src")).replace("OUT", str(out)) for a in line.split()], capsys)
    assert f"argument {flag}: " in err and why in err
    assert not out.exists()


def leaf_commands(parser: argparse.ArgumentParser, path=()):
    """(command path, parser) of every leaf subcommand."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from leaf_commands(sub, path + (name,))
            return
    yield path, parser


def test_every_option_has_help_and_its_default_shown(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "200")
    commands = list(leaf_commands(build_parser()))
    names = {" ".join(p) for p, _ in commands}
    assert names >= {"synth", "ingest", "inspect", "export-chunk", "terrain scan", "terrain export", "render", "generate"}
    assert names >= {"rollout", "eval", "demo", "train dynamics", "train observation"}
    for path, parser in commands:
        with pytest.raises(SystemExit) as exc:
            main([*path, "--help"])
        assert exc.value.code == 0
        text = " ".join(capsys.readouterr().out.split())
        for action in parser._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            assert action.help, f"{' '.join(path)} {action.dest}: no help"
            d = action.default
            if action.option_strings and action.nargs != 0 and d is not None and d != []:
                shown = "x".join(map(str, d)) if isinstance(d, tuple) else str(d)
                assert f"(default: {shown})" in text, f"{' '.join(path)} {action.option_strings[0]}: default {shown} not shown"


def test_inspect_segments_lists_every_segment(corpus, capsys):
    c = Corpus(corpus)
    assert main(["inspect", str(corpus), "--segments"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == ["segment", "split", "frames", "stage", "chunks"]
    listed = {line.split()[0]: line.split()[1:] for line in lines[1:-1]}
    rows = c.segments.to_pylist()
    assert listed == {r["segment"]: [r["split"], str(r["frames"]), r["stage"], str(r["chunks"])] for r in rows}
    assert lines[-1] == f"{len(rows)} segments, {sum(r['frames'] for r in rows)} frames"

    split = rows[0]["split"]
    assert main(["inspect", str(corpus), "--split", split, "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert [r["segment"] for r in got] == c.segment_ids(split) and {r["split"] for r in got} == {split}
    assert main(["inspect", str(corpus), "--segments", "--split", "nosuch"]) == 2
    err = capsys.readouterr().err
    assert "no segment in split 'nosuch'; its splits are" in err and split in err


def test_a_wrong_segment_id_suggests_the_near_one(corpus, tmp_path, capsys):
    seg = chunked_segment(corpus)
    wrong = seg + "x"
    for line in (
        "render CORPUS --segment WRONG --out TMP/seg.mkv",
        "rollout TMP/runs CORPUS --segment WRONG --horizon 5 --out TMP/s.arrow",
        "export-chunk CORPUS --segment WRONG",
        "export-chunk CORPUS --segment WRONG --chunk 0 --out TMP/chunk",
    ):
        argv = [a.replace("CORPUS", str(corpus)).replace("WRONG", wrong).replace("TMP", str(tmp_path)) for a in line.split()]
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert f"no segment {wrong!r}; did you mean {seg}" in err and "--segments" in err, err
    assert list(tmp_path.iterdir()) == []
    assert main(["terrain", "export", str(corpus), "--stage", "defualt", "--out", str(tmp_path / "stage.ply")]) == 2
    assert "no stage 'defualt'; did you mean default" in capsys.readouterr().err


def test_export_chunk_writes_what_generate_reads(posed, tmp_path, capsys):
    c = Corpus(posed)
    seg = chunked_segment(posed)
    assert main(["export-chunk", str(posed), "--segment", seg]) == 0
    listing = capsys.readouterr().out
    n = c.segment_row(seg)["chunks"]
    assert all(f"--chunk {k}: source frames" in listing for k in range(n)) and "no pose target" not in listing

    k = n - 1
    out = tmp_path / "chunk"
    assert main(["export-chunk", str(posed), "--segment", seg, "--chunk", str(k), "--out", str(out)]) == 0
    assert f"--pose {out / 'pose.gbz'} --first-frame {out / 'first.png'}" in capsys.readouterr().out
    n = c.segment_row(seg)["shard"]
    member = read_joined(c.video_path(n), c.pose_path(n), c.shard_hash(n), seg)[chunk_key(seg, k)]
    assert (out / "pose.gbz").read_bytes() == member["pose.gbz"] and (out / "rgb.mp4").read_bytes() == member["rgb.mp4"]
    frames, meta = decode_gbuffer(out / "pose.gbz")
    video = c.info.video
    assert len(frames) == video["chunk_frames"] and (meta.height, meta.width) == (video["height"], video["width"])
    first = read_image(out / "first.png")
    assert np.array_equal(first, decode_frames(member["rgb.mp4"])[0])  # PNG is lossless
    size = (video["height"] // 2, video["width"] // 2)  # a model at half the chunk size, as the demo trains
    pose, rgb = load_inputs(out / "pose.gbz", out / "first.png", size)
    assert tuple(pose.shape) == (video["chunk_frames"], 3, *size) and tuple(rgb.shape) == (3, *size)


def test_export_chunk_without_a_pose_target_says_how_to_render_one(unposed, tmp_path, capsys):
    seg = chunked_segment(unposed)
    assert main(["export-chunk", str(unposed), "--segment", seg]) == 0
    assert "no pose target" in capsys.readouterr().out
    assert main(["export-chunk", str(unposed), "--segment", seg, "--chunk", "0", "--out", str(tmp_path / "chunk")]) == 2
    err = capsys.readouterr().err
    assert "has no pose target" in err and "marionette terrain scan" in err
    assert not (tmp_path / "chunk").exists()
    assert main(["export-chunk", str(unposed), "--segment", seg, "--chunk", "999", "--out", str(tmp_path / "chunk")]) == 2
    assert "no chunk 999 (its chunks: 0" in capsys.readouterr().err


def test_an_unwritable_output_is_one_line_naming_the_file(posed, tmp_path, capsys, monkeypatch):
    (tmp_path / "a-file").write_text("not a directory")
    out = tmp_path / "a-file" / "chunk"
    argv = ["export-chunk", str(posed), "--segment", chunked_segment(posed), "--chunk", "0", "--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("marionette export-chunk: error: ") and str(out) in err and len(err.splitlines()) == 1
    monkeypatch.setenv("MARIONETTE_DEBUG", "1")
    with pytest.raises(OSError):
        main(argv)


def test_errors_the_command_expects_and_those_it_does_not(tmp_path):
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    (tmp_path / "model.safetensors").write_bytes(b"\x80\x04not a safetensors file")
    with pytest.raises(SafetensorError) as exc:
        load_file(str(tmp_path / "model.safetensors"))
    assert "safetensors" in error_message(exc.value)
    assert error_message(KeyError(f"{tmp_path}: no segment 'x'")) == f"{tmp_path}: no segment 'x'"  # unquoted
    assert error_message(PermissionError(13, "Permission denied", str(tmp_path / "f"))) == f"{tmp_path / 'f'}: Permission denied"
    assert error_message(ZeroDivisionError("a bug")) is None  # raised, with its traceback


def test_an_empty_source_or_a_sample_directory_exits_2_naming_it(synth_source, tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["ingest", str(tmp_path / "empty"), str(tmp_path / "c1"), "--quiet"]) == 2
    assert str(tmp_path / "empty") in capsys.readouterr().err
    sample = sorted(p for p in (synth_source / "data_part1").iterdir() if p.is_dir())[0]
    assert main(["ingest", str(sample), str(tmp_path / "c2"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert str(sample) in err and "sample directory" in err


def assert_same_rows(a, b) -> None:
    """Two tables hold the same values column by column, NaN equal to NaN (``Table.equals`` holds NaN unequal to itself)."""
    assert a.schema == b.schema
    for name in a.column_names:
        x, y = a[name].combine_chunks(), b[name].combine_chunks()
        if pa.types.is_fixed_size_list(x.type):
            x, y = x.flatten(), y.flatten()
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=name)


def test_eval_rollouts_report_progress_and_the_same_numbers(posed, tmp_path):
    from marionette.dynamics.config import TrainConfig
    from marionette.dynamics.train import train
    from marionette.eval.protocol import run_windows, select_windows, state_layer

    runs = tmp_path / "runs"
    train(posed, runs, TrainConfig(preset="tiny", steps=2, batch_size=2, window=16, warmup=1), log=lambda *_: None)
    windows = select_windows(posed, 3, seed_frames=4, horizon=6, split="train")
    told = []
    tables, ran = run_windows(runs, posed, windows, progress=lambda *a: told.append(a), phase="Free rollouts")
    plain, ran_plain = run_windows(runs, posed, windows)
    assert ran == ran_plain and len(tables) == len(plain) == 3
    for t, p in zip(tables, plain):
        assert_same_rows(t, p)
    assert {p for p, _, _ in told} == {"Free rollouts"} and {t for _, _, t in told} == {3 * 6}
    done = [d for _, d, _ in told]
    assert done == sorted(set(done)) and done[-1] == 3 * 6  # one report per frame step, up to every window's horizon
    told.clear()
    state_layer(runs, posed, windows, tables, render_size=None, progress=lambda *a: told.append(a))
    assert told == [("state-layer metrics", k, 3) for k in (1, 2, 3)]


def test_eval_flags_are_generated_from_the_protocol_fields():
    from dataclasses import fields

    from marionette.eval.config import OVERRIDES, EvalProtocol

    args = build_parser().parse_args(["eval", "d", "c", "--out", "r", "--segments", "3", "--state-seconds", "9.5"])
    assert args.probe_windows == 3 and args.state_seconds == 9.5 and args.rollouts is None
    knobs = {f.name: f for f in fields(EvalProtocol)}
    helps = {a.dest: a.help for a in build_parser()._subparsers._group_actions[0].choices["eval"]._actions}
    for name in OVERRIDES:  # each flag's help is its field's, and the protocol it overrides accepts what it parses
        assert helps[name].startswith(knobs[name].metadata["help"].replace("%", "%%"))
