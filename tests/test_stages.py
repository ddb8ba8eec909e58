"""Stages from the data: recordings grouped by the agreement of their scanned terrain (``terrain_scan.grouping``),
written to ``meta/stages.json``, a user's edit of it respected; two stages that overlap in coordinates never
share a height field."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from marionette.cli import main
from marionette.corpus.stages import read_placements
from marionette.synth import generate, load_truth
from marionette.synth.cast import make_cast
from terrain_scan.field import open_stage
from terrain_scan.grouping import MIN_SHARED, agreement, place
from terrain_scan.layers import Observations

pytestmark = pytest.mark.corpus  # generates its own recordings

PART = "data_part1"


def _obs(gx, gz, h, hits=None) -> Observations:
    gx, gz, h = (np.asarray(v) for v in (gx, gz, h))
    n = len(h)
    hits = np.full(n, 5, np.int64) if hits is None else np.asarray(hits, np.int64)
    return Observations(
        gx.astype(np.int64), gz.astype(np.int64), h.astype(float), np.tile([0.0, 1.0, 0.0], (n, 1)), hits, np.zeros(n, np.int64)
    )


def _patch(x0, z0, size, height) -> Observations:
    gx, gz = np.meshgrid(np.arange(x0, x0 + size), np.arange(z0, z0 + size))
    return _obs(gx.ravel(), gz.ravel(), height(gx.ravel(), gz.ravel()))


def test_agreement_reads_layers_and_the_best_supported_height():
    ground = _patch(-900, 800, 10, lambda x, z: 30.0 + 0.1 * x * 0)
    deck = _patch(-900, 800, 10, lambda x, z: np.full(len(x), 36.0))
    stage = Observations.concat([ground, deck])  # a bridge deck over the ground: two layers per cell
    seen_under = _patch(-900, 800, 10, lambda x, z: np.full(len(x), 30.2))
    assert agreement(seen_under, stage) == (100, 100)
    # a cell's best-supported observation decides: a stray low-hit point does not
    stray = _obs(seen_under.gx[:1], seen_under.gz[:1], [45.0], [1])
    assert agreement(Observations.concat([seen_under, stray]), stage) == (100, 100)
    other_map = _patch(-900, 800, 10, lambda x, z: np.full(len(x), 32.0))
    assert agreement(other_map, stage) == (100, 0)
    assert agreement(_patch(0, 0, 5, lambda x, z: np.zeros(len(x))), stage) == (0, 0)
    assert agreement(Observations.empty(), stage) == (0, 0)


def test_place_groups_by_agreement_never_by_coordinates():
    a = lambda x, z: 30.0 + 0.2 * (x + 900)  # noqa: E731 — a slope
    b = lambda x, z: 30.0 + 0.2 * (z - 800)  # noqa: E731 — another map, the same coordinates
    recs = [
        ("r0", _patch(-900, 800, 12, a)),
        ("r1", _patch(-900, 800, 12, b)),
        ("r2", _patch(-896, 804, 12, a)),  # overlaps r0 and r1, agrees with r0
        ("r3", _patch(-3000, -3000, 12, a)),  # overlaps nothing: its own stage, never merged on faith
        ("r4", _patch(-894, 806, 12, b)),
    ]
    names = iter(["s1", "s2", "s3"])
    out = place(recs, {}, lambda used: next(names))
    assert [(p.recording, p.stage, p.new) for p in out] == [
        ("r0", "s1", True),
        ("r1", "s2", True),
        ("r2", "s1", False),
        ("r3", "s3", True),
        ("r4", "s2", False),
    ]
    assert out[2].evidence["s1"][0] >= MIN_SHARED and out[2].evidence["s2"][1] < out[2].evidence["s2"][0]
    assert "r2 → stage s1" in out[2].line()
    # an existing stage is consulted through its loader
    again = place([("r5", _patch(-898, 802, 12, b))], {"s2": lambda obs: recs[1][1]}, lambda used: "new")
    assert again[0].stage == "s2" and not again[0].new


@pytest.fixture(scope="module")
def two_stage_corpus(tmp_path_factory) -> tuple[Path, Path]:
    """4 recordings of the drake on two stages that overlap in coordinates (recordings 0, 2 on the first), ingested
    without a stages.json."""
    root = tmp_path_factory.mktemp("two_stages")
    src, corpus = root / "src", root / "corpus"
    generate(src, recordings=4, seconds=6.0, seed=1, width=128, height=72, workers=2, stages=2)
    assert main(["ingest", str(src), str(corpus), "--quiet", "--no-pose", "--workers", "2"]) == 0
    return src, corpus


def test_stages_are_recovered_exactly_and_never_share_a_height_field(two_stage_corpus, capsys):
    src, corpus = two_stage_corpus
    truth = {f"{PART}/rec{k:04d}": load_truth(src, PART, f"rec{k:04d}")["role"]["stage"]["name"] for k in range(4)}
    placed = read_placements(corpus)
    assert set(placed) == set(truth)
    groups = {}
    for rec, st in placed.items():
        groups.setdefault(st, set()).add(rec)
    want = {}
    for rec, st in truth.items():
        want.setdefault(st, set()).add(rec)
    assert sorted(map(sorted, groups.values())) == sorted(map(sorted, want.values()))
    assert placed[f"{PART}/rec0000"] == "default"
    segments = pq.read_table(corpus / "meta" / "segments.parquet").to_pylist()
    assert {(r["sample"], r["stage"]) for r in segments} == set(placed.items())
    # each stage's height field holds its own recordings and follows its own map where the maps overlap
    cast = make_cast(1, stages=2)
    fields = {}
    for st, recs in groups.items():
        S = json.loads((corpus / "terrain" / f"stage_{st}" / "manifest.json").read_text())
        assert set(S["recordings"]) == recs
        fields[st] = (open_stage(corpus / "terrain" / f"stage_{st}"), cast.stages["ab".index(truth[next(iter(recs))])])
    gx, gz = np.meshgrid(np.arange(-990, -900), np.arange(800, 900))
    tops = {st: _top(field, gx, gz) for st, (field, _) in fields.items()}
    both = np.logical_and.reduce([np.isfinite(t) for t in tops.values()])
    assert both.sum() > 50  # they overlap in coordinates …
    for st, (_, stage) in fields.items():
        true = np.max(np.nan_to_num(np.stack(stage.layers(gx + 0.5, gz + 0.5)), nan=-np.inf), axis=0)
        assert np.median(np.abs(tops[st][both] - true[both])) < 0.3  # … and each is its own map there
    ha, hb = (t[both] for t in tops.values())
    assert np.median(np.abs(ha - hb)) > 1.0


def _top(field, gx, gz) -> np.ndarray:
    """The highest layer of each cell, nan where the field has none."""
    h, _ = field.cell_layers(gx, gz)
    return np.where(np.isfinite(h).any(-1), np.max(np.nan_to_num(h, nan=-np.inf), axis=-1), np.nan)


def test_a_rescan_keeps_the_placement_and_a_users_edit_is_respected(two_stage_corpus, tmp_path):
    src, built = two_stage_corpus
    corpus = tmp_path / "corpus"
    shutil.copytree(built, corpus)
    before = (corpus / "meta" / "stages.json").read_bytes()
    assert main(["terrain", "scan", str(corpus), "--incremental", "--no-pose", "--quiet"]) == 0
    assert (corpus / "meta" / "stages.json").read_bytes() == before
    # the user moves one recording to a stage of its own
    placed = read_placements(corpus)
    moved = f"{PART}/rec0003"
    old = placed[moved]
    placed[moved] = "arena3"
    (corpus / "meta" / "stages.json").write_text(json.dumps({"recordings": placed}))
    assert main(["terrain", "scan", str(corpus), "--incremental", "--no-pose", "--quiet"]) == 0
    assert read_placements(corpus)[moved] == "arena3"
    segments = pq.read_table(corpus / "meta" / "segments.parquet").to_pylist()
    assert {r["stage"] for r in segments if r["sample"] == moved} == {"arena3"}
    manifest = lambda st: json.loads((corpus / "terrain" / f"stage_{st}" / "manifest.json").read_text())  # noqa: E731
    assert set(manifest("arena3")["recordings"]) == {moved}
    assert moved not in manifest(old)["recordings"]
    # a placement file that is not one is an error naming it
    (corpus / "meta" / "stages.json").write_text(json.dumps({"recordings": {"../x": "a"}}))
    assert main(["terrain", "scan", str(corpus), "--incremental", "--no-pose", "--quiet"]) == 2


def test_a_source_stages_json_is_the_users_word(two_stage_corpus, tmp_path):
    src, _ = two_stage_corpus
    tree = tmp_path / "src"
    shutil.copytree(src / PART, tree / PART)
    (tree / "stages.json").write_text(json.dumps({f"{PART}/rec{k:04d}": "all" for k in range(4)}))
    corpus = tmp_path / "corpus"
    assert main(["ingest", str(tree), str(corpus), "--quiet", "--no-pose"]) == 0
    assert {r["stage"] for r in pq.read_table(corpus / "meta" / "segments.parquet").to_pylist()} == {"all"}
    assert read_placements(corpus) == {}  # nothing left to place


def test_a_depth_mapping_that_does_not_fit_is_named_and_founds_no_stage(tmp_path, capsys):
    """A tree whose game hid its depth mapping, ingested with the default decoder: every recording is named with
    how far its ground stood from its feet and the command to run, none founds a stage; calibrated and rescanned, the
    stages are the truth's."""
    src, corpus = tmp_path / "src", tmp_path / "corpus"
    generate(src, recordings=4, seconds=6.0, seed=1, width=128, height=72, workers=2, stages=2, hidden_depth=True)
    assert (
        main(["ingest", str(src), str(corpus), "--quiet", "--no-pose", "--workers", "2", "--strict"]) == 1
    )  # --strict fails on them
    said = capsys.readouterr().out
    names = [f"{PART}/rec{k:04d}" for k in range(4)]
    for name in names:
        line = next(x for x in said.splitlines() if x.startswith(f"terrain failed: default/{name}: "))
        assert "the depth mapping does not fit this recording" in line and "marionette calibrate-depth" in line, line
        assert re.search(r"ground stands \+\d+\.\d\d m from where|no ground on any of the \d+ cells", line), line
    assert "depth mapping: it does not fit 4 recording(s), kept out of the terrain" in said
    assert read_placements(corpus) == {}  # no stage founded on a recording the mapping does not fit
    assert not json.loads((corpus / "terrain" / "stage_default" / "manifest.json").read_text())["recordings"]

    assert main(["calibrate-depth", str(src), "--corpus", str(corpus), "--quiet", "--frame-stride", "3"]) == 0
    assert main(["terrain", "scan", str(corpus), "--quiet", "--no-pose", "--strict"]) == 0
    placed = read_placements(corpus)
    truth = {name: load_truth(src, PART, name.split("/")[1])["role"]["stage"]["name"] for name in names}
    assert set(placed) == set(names)
    assert {frozenset(r for r in names if placed[r] == st) for st in set(placed.values())} == {
        frozenset(r for r in names if truth[r] == st) for st in set(truth.values())
    }
