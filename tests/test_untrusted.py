"""A corpus, a checkpoint directory and a model directory are untrusted input: a name read from one becomes a
path only when it matches its pattern and stays inside its root. Each case plants a hostile entry, checks that
the error names it, and that a sentinel tree outside the corpus is byte-for-byte unchanged."""

from __future__ import annotations

import io
import json
import os
import re
import shutil
import struct
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import pyarrow as pa
import pytest
import torch
from fixtures.corpora import TEST_OPTIONS
from safetensors.torch import save_file

from marionette.checkpoint import CHECKPOINT_VERSION, latest_checkpoint, read_meta
from marionette.corpus import Corpus, paths, video_shards
from marionette.corpus.lock import CorpusLocked, corpus_lock
from marionette.corpus.stages import STAGES_FILE, read_stage_file
from marionette.ingest import build_corpus, load_stage_map
from marionette.io import write_ipc


def _sentinel(root: Path) -> Path:
    """A tree of files and a directory that a traversal would move, delete or overwrite."""
    out = root / "outside"
    (out / "dir").mkdir(parents=True)
    (out / "victim").write_bytes(b"keep me")
    (out / "dir" / "inner").write_bytes(b"keep me too")
    (out / "evil.json").write_bytes(b"{}")
    return out


def _snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() if p.is_file() else b"<dir>" for p in sorted(root.rglob("*"))}


@pytest.fixture
def corpus_copy(corpus, tmp_path) -> Path:
    """A private copy of the session corpus at tmp_path/corpus, beside the sentinel tmp_path/outside."""
    out = tmp_path / "corpus"
    shutil.copytree(corpus, out)
    return out


def _raw_member(tar: tarfile.TarFile, name: str, data: bytes) -> None:
    info = tarfile.TarInfo(name)
    info.size = len(data)
    tar.addfile(info, io.BytesIO(data))


# pose targets are written under corpus/derived/pose: three levels up is the sentinel
@pytest.mark.parametrize(
    "evil", ["../../../outside/evil.json", "/outside/evil.json", "x__c00000.rgb.mp4/../../../../outside/evil.json"]
)
def test_video_shard_member_outside_the_corpus_is_refused(corpus_copy, tmp_path, evil):
    from marionette.bridge.targets import render_pose_targets

    outside = _sentinel(tmp_path)
    before = _snapshot(tmp_path / "outside")
    shard = corpus_copy / "video" / "shard-000000.tar"
    members = video_shards.read_members(shard)
    name = evil if not evil.startswith("/") else str(tmp_path / evil.lstrip("/"))
    with tarfile.open(shard, "w", format=tarfile.GNU_FORMAT) as tar:
        for n, data in members:
            _raw_member(tar, n, data)
        _raw_member(tar, name, json.dumps({"segment": "x", "chunk": 0, "frames": [0, 81]}).encode())
    shard_bytes = shard.read_bytes()

    with pytest.raises(paths.CorpusPathError, match="member"):
        video_shards.read_members(shard)
    report = render_pose_targets(corpus_copy)
    assert name in report.failed["shard-000000"], report.failed
    assert shard.read_bytes() == shard_bytes  # the refused shard is left as it was
    assert _snapshot(outside) == before
    assert not any(p.name.startswith("evil-") for p in tmp_path.rglob("*.gbz"))
    assert report.chunks > 0 and not any(k.startswith("shard-") for k in report.failed if k != "shard-000000")


@pytest.mark.parametrize("evil", ["../../../outside/evil.pose.gbz", "x__c00000.rgb.mp4"])
def test_pose_shard_member_outside_its_kinds_is_refused(corpus_copy, tmp_path, evil):
    """A pose shard holds ``<key>.pose.json`` and ``<key>.pose.gbz`` only: anything else refuses the shard (readers
    skip its chunks, naming it) and the next pose pass writes it again."""
    from marionette.bridge.targets import render_pose_targets
    from marionette.corpus import Corpus
    from marionette.observation.data import ClipSource

    render_pose_targets(corpus_copy)
    c = Corpus(corpus_copy)
    pose = c.pose_path(0)
    good = pose.read_bytes()
    members = video_shards.read_members(pose)
    with tarfile.open(pose, "w", format=tarfile.GNU_FORMAT) as tar:
        for n, data in members:
            _raw_member(tar, n, data)
        _raw_member(tar, evil, b"x")
    with pytest.raises(paths.CorpusPathError, match="member"):
        video_shards.PoseShard(pose)
    src = ClipSource(c, None, 1, (c.info.video["height"], c.info.video["width"]))
    keys = [s["__key__"] for s, _ in src._samples()]
    assert "shard-000000.tar" in src.skipped and "member" in src.skipped["shard-000000.tar"]
    shard0 = {s for s in c.segment_ids() if c.segment_row(s)["shard"] == 0}
    assert not any(paths.parse_chunk_key(k)[0] in shard0 for k in keys)
    report = render_pose_targets(corpus_copy)
    assert report.shards_rewritten == [0] and pose.read_bytes() == good
    assert not (tmp_path / "outside").exists() or not any((tmp_path / "outside").iterdir())


def test_video_shard_member_must_name_its_own_chunk(corpus_copy):
    shard = corpus_copy / "video" / "shard-000000.tar"
    key, _ = video_shards.parse_member(video_shards.read_members(shard)[0][0])
    other = key.replace("__c", "X__c")
    with pytest.raises(ValueError, match=f"member {other}.json names segment"):
        video_shards.chunk_record(json.dumps({"segment": paths.parse_chunk_key(key)[0], "chunk": 0}).encode(), other, "shard")


def test_finalize_plan_entries_outside_the_corpus_are_refused(corpus_copy, synth_source, tmp_path):
    outside = _sentinel(tmp_path)
    before = _snapshot(outside)
    inside_before = _snapshot(corpus_copy / "state")
    plan = {  # plan entries are relative to the corpus
        "moves": [["../outside/victim", "state/shard-000000.arrow", "h"]],
        "deletes": ["../outside/dir/inner"],
        "records": [{"key": "../outside/dir"}],
    }
    plan_path = corpus_copy / "meta" / "finalize-plan.json"
    for bad, entry in (
        (plan, "moves[0]"),
        ({**plan, "moves": []}, "deletes[0]"),
        ({**plan, "moves": [], "deletes": []}, "records[0]"),
    ):
        plan_path.write_text(json.dumps(bad))
        with pytest.raises(paths.CorpusPathError, match=re.escape(f"finalize-plan.json: {entry}")):
            build_corpus(synth_source, corpus_copy, TEST_OPTIONS, workers=1, progress=False)
        assert _snapshot(outside) == before
        assert _snapshot(corpus_copy / "state") == inside_before
    plan_path.write_text(
        json.dumps({"moves": [["staging/k/state.arrow", "../outside/victim", "h"]], "deletes": [], "records": []})
    )
    with pytest.raises(paths.CorpusPathError, match="outside/victim"):
        build_corpus(synth_source, corpus_copy, TEST_OPTIONS, workers=1, progress=False)
    assert _snapshot(outside) == before


def test_sample_record_whose_key_is_not_its_file_is_refused(corpus_copy, synth_source):
    record = sorted((corpus_copy / "meta" / "samples").glob("*.json"))[0]
    rec = json.loads(record.read_text())
    record.write_text(json.dumps({**rec, "key": "../outside"}))
    with pytest.raises(paths.CorpusPathError, match=f"{record.name}: record key"):
        build_corpus(synth_source, corpus_copy, TEST_OPTIONS, workers=1, progress=False)


def test_terrain_manifest_file_outside_the_stage_is_refused(scanned_corpus, tmp_path):
    from marionette.pipeline import refresh

    corpus = tmp_path / "corpus"
    shutil.copytree(scanned_corpus, corpus)
    outside = _sentinel(tmp_path)
    before = _snapshot(outside)
    manifest = corpus / "terrain" / "stage_default" / "manifest.json"
    m = json.loads(manifest.read_text())
    rec = next(iter(m["recordings"]))
    # stage files are relative to corpus/terrain/stage_default: three levels up is the sentinel
    m["recordings"][rec]["file"] = "../../../outside/victim"
    m["recordings"]["gone/recording"] = {**m["recordings"][rec], "file": "../../../outside/dir/inner"}
    manifest.write_text(json.dumps(m))
    with pytest.raises(paths.CorpusPathError, match=re.escape(f"recordings.{rec}.file is '../../../outside/victim'")):
        refresh(corpus, incremental=True)
    assert _snapshot(outside) == before

    m = json.loads(scanned_corpus.joinpath("terrain", "stage_default", "manifest.json").read_text())
    chunk = next(iter(m["chunks"]))
    m["chunks"][chunk]["file"] = "../../../outside/victim"
    manifest.write_text(json.dumps(m))
    with pytest.raises(paths.CorpusPathError, match=re.escape(f"chunks.{chunk}.file")):
        refresh(corpus, incremental=True)
    assert _snapshot(outside) == before


def test_checkpoint_latest_naming_the_parent_is_refused(tmp_path):
    runs = tmp_path / "runs"
    runs.mkdir()
    (tmp_path / "meta.json").write_text("{}")  # what `latest` = ".." would point at
    for bad in ("..", "../runs", "/etc", "step-1"):
        (runs / "latest").write_text(bad + "\n")
        with pytest.raises(ValueError, match=r"runs/latest: names"):
            latest_checkpoint(runs)


def test_wan_index_shard_outside_the_directory_is_refused(tmp_path):
    from marionette.observation.wan import WEIGHTS, read_safetensors

    model = tmp_path / "model"
    model.mkdir()
    save_file({"w": torch.zeros(2)}, str(tmp_path / "x.safetensors"))  # a real file the entry would reach
    for bad in ("../x.safetensors", str(tmp_path / "x.safetensors"), "sub/../../x.safetensors", ".hidden.safetensors"):
        (model / f"{WEIGHTS}.index.json").write_text(json.dumps({"weight_map": {"w": bad}}))
        with pytest.raises(ValueError, match="weight_map names"):
            read_safetensors(model)


def test_pickle_renamed_safetensors_names_the_file(tmp_path):
    from marionette.io import read_tensors

    path = tmp_path / "model.safetensors"
    torch.save({"w": torch.zeros(2)}, path)  # a torch pickle under a safetensors name
    with pytest.raises(ValueError, match=r"model\.safetensors: not a readable safetensors file"):
        read_tensors(path)


def test_id_patterns_admit_no_traversal():
    for bad in ("..", ".", "a/b", "/abs", "a.b", "", "a b", "x" * 201):
        with pytest.raises(paths.CorpusPathError):
            paths.check_id(bad, "segment")
    with pytest.raises(paths.CorpusPathError):
        paths.parse_chunk_key("../x__c00000")
    with pytest.raises(paths.CorpusPathError):
        paths.state_shard(Path("c"), -1)
    assert paths.parse_chunk_key("data_part1-rec0000-s000__c00003") == ("data_part1-rec0000-s000", 3)


def test_symlink_out_of_the_corpus_is_refused(tmp_path):
    root = tmp_path / "corpus"
    (root / "state").mkdir(parents=True)
    (tmp_path / "elsewhere").mkdir()
    os.symlink(tmp_path / "elsewhere", root / "state" / "link")
    with pytest.raises(paths.CorpusPathError, match="outside"):
        paths.inside(root, root / "state" / "link" / "x")


def test_a_second_writer_fails_fast_naming_the_holder(tmp_path):
    corpus = tmp_path / "corpus"
    with corpus_lock(corpus, "ingest"):
        code = "import sys; from marionette.corpus.lock import corpus_lock\nwith corpus_lock(sys.argv[1], 'scan'): pass"
        r = subprocess.run([sys.executable, "-c", code, str(corpus)], capture_output=True, text=True, timeout=60)
        assert r.returncode != 0 and f"pid {os.getpid()} (ingest)" in r.stderr
        with pytest.raises(CorpusLocked, match="another build"), corpus_lock(corpus, "scan"):  # not re-entrant unless shared
            pass
    with corpus_lock(corpus, "pipeline", share=True), corpus_lock(corpus, "scan"):  # a shared hold admits its own writers
        assert "pid" in (corpus / "meta" / ".lock").read_text()


def test_terrain_scan_started_during_an_ingest_is_refused(synth_source, tmp_path):
    from marionette.cli import main

    corpus = tmp_path / "corpus"
    code = (
        "import sys; from pathlib import Path; from marionette.ingest import build_corpus; from fixtures.corpora import TEST_OPTIONS\n"
        "build_corpus(Path(sys.argv[1]), Path(sys.argv[2]), TEST_OPTIONS, workers=1, progress=False)"
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent)}
    ingest = subprocess.Popen([sys.executable, "-c", code, str(synth_source), str(corpus)], env=env, stderr=subprocess.PIPE)
    try:
        lock = corpus / "meta" / ".lock"
        deadline = time.time() + 120
        while not (lock.exists() and lock.read_text().startswith("pid")):
            assert ingest.poll() is None and time.time() < deadline, "the ingest ended before the lock was seen"
            time.sleep(0.05)
        with pytest.raises(CorpusLocked, match=rf"pid {ingest.pid} \(ingest\)"):
            from marionette.pipeline import refresh

            refresh(corpus)
        assert main(["terrain", "scan", str(corpus)]) == 2
        assert ingest.poll() is None, "the ingest must still be running: the refusal came from the lock"
    finally:
        ingest.wait(timeout=300)
    assert ingest.returncode == 0, ingest.stderr.read().decode()


@pytest.mark.parametrize("special", ["fifo", "dev-zero"])
def test_a_special_file_in_a_corpus_is_named_and_never_blocks_a_command(corpus_copy, special):
    info = paths.meta(corpus_copy, paths.INFO)
    info.unlink()
    if special == "fifo":
        os.mkfifo(info)  # a blocking read would hang the command (and any lock it held) forever
    else:
        info.symlink_to("/dev/zero")  # a read trusting its size would never end
    t0 = time.monotonic()
    r = subprocess.run(
        [sys.executable, "-m", "marionette.cli", "inspect", str(corpus_copy)], capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 2 and "info.json: a " in r.stderr and "not a regular file" in r.stderr, r.stderr
    assert time.monotonic() - t0 < 60


def _bomb(shard: Path, dim: int) -> None:
    """Make the first batch's compressed state values declare 2 GiB once inflated (their buffer's int64 prefix), as a
    crafted shard of kilobytes can; nothing else in the file changes."""
    with pa.memory_map(str(shard)) as src:
        rows = pa.ipc.open_file(src).get_batch(0).num_rows
    data = shard.read_bytes()
    prefix = struct.pack("<q", rows * dim * 4)  # the float32 state values' uncompressed size
    assert prefix in data
    shard.write_bytes(data.replace(prefix, struct.pack("<q", 2 << 30), 1))


def test_a_state_shard_bomb_is_refused_before_it_is_inflated(corpus_copy, tmp_path):
    c = Corpus(corpus_copy)
    segment = c.segment_ids()[0]
    shard = c.segment_row(segment)["shard"]
    path = c.state_path(shard)
    table = c.read_shard(shard)
    _bomb(path, c.layout.dim)
    with pytest.raises(
        ValueError, match=r"declare 2,1\d\d,\d{3},\d{3} bytes once inflated, more than .* refused before it is inflated"
    ):
        Corpus(corpus_copy).read_shard(shard)
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "marionette.cli",
            "render",
            str(corpus_copy),
            "--segment",
            segment,
            "--out",
            str(tmp_path / "x.mkv"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2 and path.name in r.stderr and "refused before it is inflated" in r.stderr, r.stderr
    # a shard holding more rows than the corpus's segments say is refused as well, before it is read
    write_ipc(path, pa.concat_tables([table] * 3))
    with pytest.raises(ValueError, match=r"its batches declare [\d,]+ rows; the corpus says it holds [\d,]+"):
        Corpus(corpus_copy).read_shard(shard)


@pytest.mark.parametrize("special", ["fifo", "dev-zero"])
def test_every_json_a_command_reads_first_is_refused_by_name_as_a_special_file(corpus_copy, tmp_path, special):
    def plant(p: Path) -> Path:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.unlink(missing_ok=True)
        os.mkfifo(p) if special == "fifo" else p.symlink_to("/dev/zero")
        return p

    ckpt = tmp_path / "run" / "step-00000001"
    ckpt.mkdir(parents=True)
    (ckpt / "meta.json").write_text(json.dumps({"version": CHECKPOINT_VERSION}))
    cases = [
        (plant(paths.meta(corpus_copy, paths.VOCAB)), lambda: Corpus(corpus_copy).vocab),
        (plant(paths.meta(corpus_copy, STAGES_FILE)), lambda: read_stage_file(corpus_copy)),
        (plant(tmp_path / "src" / STAGES_FILE), lambda: load_stage_map(tmp_path / "src")),
        (plant(ckpt / "meta.json"), lambda: read_meta(ckpt)),
    ]

    def refused(path: Path, read) -> None:
        t0 = time.monotonic()
        with pytest.raises(
            ValueError, match="a FIFO, not a regular file" if special == "fifo" else "a character device, not a"
        ) as err:
            read()
        assert str(path) in str(err.value) and time.monotonic() - t0 < 1.0, err.value

    for path, read in cases:
        refused(path, read)
    (ckpt.parent / "latest").write_text(ckpt.name)
    refused(ckpt / "meta.json", lambda: latest_checkpoint(ckpt.parent))  # named by a training directory's latest
    refused(plant(ckpt.parent / "latest"), lambda: latest_checkpoint(ckpt.parent))


def test_a_trees_stages_json_that_cannot_be_read_ends_the_ingest_before_any_sample(synth_source, tmp_path):
    src = tmp_path / "src"
    shutil.copytree(synth_source / "data_part1", src / "data_part1")
    os.mkfifo(src / STAGES_FILE)  # read whole, it would hang the build forever
    r = subprocess.run(
        [sys.executable, "-m", "marionette.cli", "ingest", str(src), str(tmp_path / "corpus"), "--quiet", "--no-terrain"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2 and f"{src / STAGES_FILE}: a FIFO, not a regular file" in r.stderr, r.stderr
    assert not list((tmp_path / "corpus").glob("staging/*"))  # no sample's work was done
