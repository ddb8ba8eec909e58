"""Bad input is quarantined with a reason naming the file and row or frame; crashes are repaired by a rerun."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
from fixtures.corpora import TEST_OPTIONS

from marionette.corpus import Corpus
from marionette.ingest import build_corpus


def _copy_sample(src_root: Path, dst_root: Path, name: str) -> Path:
    part = dst_root / "data_part1"
    part.mkdir(parents=True, exist_ok=True)
    if not (part / "skeleton_edges.json").exists():
        shutil.copy(src_root / "data_part1" / "skeleton_edges.json", part)
    shutil.copytree(src_root / "data_part1" / "rec0000", part / name)
    return part / name


def _rewrite_csv(path: Path, edit) -> None:
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join(edit(lines)))


def test_bad_samples_are_quarantined_and_the_rest_ingested(synth_source, tmp_path):
    src = tmp_path / "src"
    _copy_sample(synth_source, src, "good")
    d = _copy_sample(synth_source, src, "truncated_npz")
    data = (d / "skeleton.npz").read_bytes()
    (d / "skeleton.npz").write_bytes(data[: len(data) // 2])
    d = _copy_sample(synth_source, src, "malformed_row")
    _rewrite_csv(d / "state.csv", lambda ls: ls[:40] + [ls[40].rstrip("\n") + ",extra\n"] + ls[41:])
    d = _copy_sample(synth_source, src, "bad_tuple")
    header = (d / "state.csv").read_text().splitlines()[0].split(",")

    def break_pos(ls):
        import csv
        import io

        rows = list(csv.reader(io.StringIO("".join(ls))))
        col = rows[0].index("npc.list.0.pos")
        rows[17][col] = "(1.0, oops, 2.0)"
        out = io.StringIO()
        csv.writer(out, lineterminator="\n").writerows(rows)
        return [out.getvalue()]

    _rewrite_csv(d / "state.csv", break_pos)
    assert "npc.list.0.pos" in header
    d = _copy_sample(synth_source, src, "short_csv")
    _rewrite_csv(d / "state.csv", lambda ls: ls[:-5])
    d = _copy_sample(synth_source, src, "no_rgb")
    (d / "rgb.mp4").unlink()

    def no_segment(ls):
        import csv
        import io

        rows = list(csv.reader(io.StringIO("".join(ls))))
        cols = [rows[0].index(c) for c in ("camera.K", "camera.pos", "camera.rot")]
        for i in range(1, len(rows), 20):  # the camera fails every 20 frames: no run reaches 30
            for c in cols:
                rows[i][c] = "nan"
        out = io.StringIO()
        csv.writer(out, lineterminator="\n").writerows(rows)
        return [out.getvalue()]

    d = _copy_sample(synth_source, src, "no_segment")
    _rewrite_csv(d / "state.csv", no_segment)

    corpus = tmp_path / "corpus"
    report = build_corpus(src, corpus, TEST_OPTIONS, workers=2, progress=False)
    status = {r["sample"].split("/")[1]: r for r in report["results"]}
    assert status["good"]["status"] == "ingested"
    reasons = {k: v["reason"] for k, v in status.items() if v["status"] == "quarantined"}
    assert set(reasons) == {"truncated_npz", "malformed_row", "bad_tuple", "short_csv", "no_rgb", "no_segment"}
    assert "skeleton.npz" in reasons["truncated_npz"] and "truncated_npz" in reasons["truncated_npz"]
    assert "state.csv" in reasons["malformed_row"] and "row 40" in reasons["malformed_row"]
    assert "state.csv" in reasons["bad_tuple"] and "row 17" in reasons["bad_tuple"] and "npc.list.0.pos" in reasons["bad_tuple"]
    assert "frame counts disagree" in reasons["short_csv"] and "state.csv rows" in reasons["short_csv"]
    assert "rgb.mp4" in reasons["no_rgb"] and "missing" in reasons["no_rgb"]
    assert "no valid segment" in reasons["no_segment"] and "camera invalid" in reasons["no_segment"]
    c = Corpus(corpus)
    q = {r["sample"].split("/")[1]: r["reason"] for r in pq.read_table(corpus / "meta" / "quarantine.parquet").to_pylist()}
    assert q == reasons
    assert c.info.total_ingested == 1 and len(c.shard_ids()) == 1
    assert c.read_shard(c.shard_ids()[0]).num_rows == c.info.total_frames
    assert not list(corpus.rglob("*.tmp"))
    assert not (corpus / "staging").exists() or not list((corpus / "staging").iterdir())


def _tree(corpus: Path) -> dict[str, bytes]:
    out = {}
    for sub in ("state", "video"):
        for p in sorted((corpus / sub).glob("*")):
            out[f"{sub}/{p.name}"] = p.read_bytes()
    return out


def test_sigkill_mid_build_then_rerun_gives_the_same_corpus(synth_source, corpus, tmp_path):
    """``marionette ingest`` killed mid-write, then rerun: the same bytes as a clean build (the session corpus, built
    from the same source with the same options, ingest alone: no terrain scan, no pose targets)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    cli = [
        sys.executable,
        "-m",
        "marionette.cli",
        "ingest",
        str(synth_source),
        "",
        "--workers",
        "2",
        "--quiet",
        "--video-size",
        "72x128",
        "--crf",
        "23",
        "--no-terrain",
        "--no-pose",
    ]
    clean = corpus
    crashed = tmp_path / "crashed"
    proc = subprocess.Popen(
        cli[:5] + [str(crashed)] + cli[6:], env=env, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    deadline = time.time() + 120
    killed_mid_write = False
    while time.time() < deadline and proc.poll() is None:
        if list(crashed.glob("staging/*/.*.tmp")):
            killed_mid_write = True
            break
        time.sleep(0.002)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert killed_mid_write, "the build finished before a write could be interrupted"
    assert not (crashed / "meta" / "info.json").exists()
    subprocess.run(cli[:5] + [str(crashed)] + cli[6:], check=True, env=env, capture_output=True)
    assert _tree(crashed) == _tree(clean)
    a, b = Corpus(clean), Corpus(crashed)
    assert a.segments.drop(["stage"]).equals(b.segments.drop(["stage"]))
    segs = b.segments["segment"].to_pylist()
    assert len(segs) == len(set(segs))
    for s in b.shard_ids():
        assert a.read_shard(s).equals(b.read_shard(s))
    assert not list(crashed.rglob("*.tmp"))
