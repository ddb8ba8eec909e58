"""Every reader of a file from outside, fed damaged copies of a valid file (truncations, bit flips, overwritten
bytes, huge declared sizes): it answers with its value or a named error (a ValueError naming the file), never another
exception, a hang or a write outside its root. Hypothesis draws the damage; each reader's cases run in about a
second."""

from __future__ import annotations

import io
import json
import os
import struct
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from marionette.arrow_footer import ArrowFooterError, declared_batches
from marionette.bridge.gbuffer import GBufferMeta, iter_planes, read_gbuffer_meta, write_gbuffer
from marionette.corpus.stages import check_stage_map
from marionette.dynamics.config import DynamicsConfig
from marionette.io import read_ipc, read_json, write_ipc
from marionette.observation.config import OBS_PRESETS, ObservationConfig
from marionette.play.guard import parse_message
from marionette.recordings.errors import SampleError
from marionette.recordings.skeleton_archive import SkeletonArchive
from marionette.recordings.wildworld import load_edges
from marionette.schema import load_scene

# the suite's examples are drawn the same way every run (derandomized); MARIONETTE_FUZZ_EXAMPLES=5000 searches afresh
EXAMPLES = int(os.environ.get("MARIONETTE_FUZZ_EXAMPLES", "120"))
FUZZ = settings(
    max_examples=EXAMPLES,
    derandomize="MARIONETTE_FUZZ_EXAMPLES" not in os.environ,
    database=None,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)


@st.composite
def damage(draw, data: bytes) -> bytes:
    """``data`` cut short, with bits flipped, or with a run of bytes overwritten (an int64 there may declare gigabytes)."""
    kind = draw(st.sampled_from(["truncate", "flip", "overwrite"]))
    if kind == "truncate":
        return data[: draw(st.integers(0, len(data) - 1))]
    out = bytearray(data)
    if kind == "flip":
        for _ in range(draw(st.integers(1, 8))):
            i = draw(st.integers(0, len(out) - 1))
            out[i] ^= 1 << draw(st.integers(0, 7))
        return bytes(out)
    i = draw(st.integers(0, len(out) - 8))
    out[i : i + 8] = struct.pack("<q", draw(st.sampled_from([-1, 0, 1 << 31, 1 << 40, (1 << 63) - 1, -(1 << 63)])))
    return bytes(out)


def _named(exc: BaseException, path: Path) -> None:
    assert str(path) in str(exc), f"{type(exc).__name__} does not name {path}: {exc}"


def _ipc_bytes(tmp: Path) -> bytes:
    t = pa.table(
        {
            "segment": ["a", "b", "c"] * 20,
            "state": pa.array(np.arange(60 * 8, dtype=np.float32).reshape(60, 8).tolist(), pa.list_(pa.float32(), 8)),
        }
    )
    write_ipc(tmp, t, "zstd")
    return tmp.read_bytes()


@pytest.fixture(scope="module")
def seeds(tmp_path_factory) -> dict[str, bytes]:
    """One valid file of each kind the readers take."""
    d = tmp_path_factory.mktemp("seeds")
    buf = io.BytesIO()
    np.savez(buf, m1_25=np.zeros((40, 64, 3), np.float32), n1_0=np.ones((40, 36, 3), np.float32))
    config = DynamicsConfig.preset("tiny", load_scene("duel"), (12, 9)).to_json()
    return {
        "json": json.dumps({"recordings": {"data_part1/rec0000": "default"}, "found": {}, "n": [1, 2.5, None]}).encode(),
        "ipc": _ipc_bytes(d / "seed.arrow"),
        "npz": buf.getvalue(),
        "edges": json.dumps({"em_25": [[0, 1], [1, 2]], "npc": [[0, 1]]}).encode(),
        "dynamics": json.dumps(config).encode(),
        "observation": json.dumps(OBS_PRESETS["tiny"].to_json()).encode(),
        "gbz": _gbz_bytes(d / "seed.gbz"),
    }


def _gbz_bytes(tmp: Path) -> bytes:
    rng = np.random.default_rng(0)
    frames = [np.where(rng.random((3, 12, 20)) < 0.5, 0, rng.integers(0, 1024, (3, 12, 20))).astype(np.uint16) for _ in range(3)]
    write_gbuffer(tmp, frames, GBufferMeta(0.0, 10.0, 0.3, 100.0, 20, 12, 30.0))
    return tmp.read_bytes()


def _write(tmp_path: Path, name: str, data: bytes) -> Path:
    p = tmp_path / name
    p.write_bytes(data)
    return p


@pytest.mark.parametrize(
    "seed, name, read", [("json", "meta.json", read_json), ("edges", "skeleton_edges.json", load_edges)], ids=["json", "edges"]
)
@FUZZ
@given(data=st.data())
def test_a_json_reader_answers_or_names_the_file(seeds, tmp_path, data, seed, name, read):
    p = _write(tmp_path, name, data.draw(damage(seeds[seed])))
    try:
        read(p)
    except ValueError as exc:  # SampleError is one
        _named(exc, p)


@FUZZ
@given(data=st.data())
def test_an_arrow_file_answers_or_names_the_file_before_inflating_it(seeds, tmp_path, data):
    p = _write(tmp_path, "shard.arrow", data.draw(damage(seeds["ipc"])))
    try:
        declared_batches(p)
    except ArrowFooterError as exc:
        _named(exc, p)
    try:
        t = read_ipc(p, rows=60)
    except ValueError as exc:
        _named(exc, p)
    else:
        assert t.num_rows == 60


@FUZZ
@given(data=st.data())
def test_a_gbuffer_file_answers_or_names_the_file_before_inflating_it(seeds, tmp_path, data):
    raw = data.draw(damage(seeds["gbz"]))
    p = _write(tmp_path, "pose.gbz", raw)
    for read in (read_gbuffer_meta, lambda f: list(iter_planes(f))):
        try:
            read(p)
        except ValueError as exc:
            _named(exc, p)
    try:
        frames = list(iter_planes(raw, name="shard.tar:pose.gbz"))
    except ValueError as exc:
        assert "shard.tar:pose.gbz" in str(exc)
    else:
        assert all(f.shape == (3, 12, 20) for f in frames)


@FUZZ
@given(data=st.data())
def test_a_skeleton_archive_answers_or_names_the_file(seeds, tmp_path, data):
    p = _write(tmp_path, "skeleton.npz", data.draw(damage(seeds["npz"])))
    try:
        archive = SkeletonArchive(p, max_member_bytes=1 << 20)
        for key in archive.keys:
            archive.read(key, max_frames=64)
    except SampleError as exc:
        _named(exc, p)


@FUZZ
@given(data=st.data())
def test_saved_configs_load_or_are_named_errors(seeds, tmp_path, data):
    for kind, cls in (("dynamics", DynamicsConfig), ("observation", ObservationConfig)):
        p = _write(tmp_path, f"{kind}.json", data.draw(damage(seeds[kind])))
        try:
            d = read_json(p)
            cls.from_json(d) if isinstance(d, dict) else None
        except ValueError:
            pass  # read_json's name the file; a config's name the field (checkpoint.read_config adds the file)


@FUZZ
@given(
    value=st.recursive(
        st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
        lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=8), c, max_size=3),
        max_leaves=12,
    )
)
def test_a_stage_map_of_any_shape_is_checked(value):
    try:
        assert check_stage_map(value, "stages.json") == value
    except ValueError as exc:
        assert "stages.json" in str(exc)


@FUZZ
@given(raw=st.binary(max_size=200) | st.text(alphabet='[]{}",:0123456789abc \\', max_size=400))
def test_a_play_message_of_any_bytes_is_a_value_or_a_value_error(raw):
    try:
        parse_message(raw)
    except ValueError as exc:
        assert "JSON" in str(exc) or "nested" in str(exc)
