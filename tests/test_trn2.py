"""The TRN2 chunk format: exact bytes, round trips, errors naming the file, floor indexing."""

import struct

import numpy as np
import pytest

from terrain_scan.trn2 import (
    FLAG_FILLED,
    FLAG_VALID,
    Chunk,
    TerrainFormatError,
    cell_of,
    chunk_of,
    read_chunk,
    split_cell,
    write_chunk,
)


def test_file_built_byte_by_byte_from_the_spec_reads_back(tmp_path):
    max_layers = 3
    head = b"TRN2" + struct.pack("<i", 2) + struct.pack("<i", -10) + struct.pack("<i", 8)
    head += struct.pack("<i", 100) + struct.pack("<f", 1.0) + struct.pack("<i", 10000) + struct.pack("<i", max_layers)
    body = bytearray(10000 * max_layers * 24)
    # cell (row 7, col 42), slot 1: h = -3.25, normal (0, 1, 0), 70000 hits saturated to 65535, valid | filled, ts
    off = ((7 * 100 + 42) * max_layers + 1) * 24
    body[off : off + 24] = struct.pack("<ffffHBBI", -3.25, 0.0, 1.0, 0.0, 65535, 3, 0, 1767225600)
    path = tmp_path / "chunk.trn2"
    path.write_bytes(head + bytes(body))
    c = read_chunk(path)
    assert (c.cx, c.cz, c.max_layers) == (-10, 8, 3)
    rec = c.cells[7 * 100 + 42, 1]
    assert rec["h"] == np.float32(-3.25) and tuple(rec["n"]) == (0, 1, 0)
    assert rec["hits"] == 65535 and rec["flags"] == FLAG_VALID | FLAG_FILLED and rec["ts"] == 1767225600
    assert c.valid().sum() == 1
    # and our writer produces exactly those bytes
    write_chunk(tmp_path / "again.trn2", c)
    assert (tmp_path / "again.trn2").read_bytes() == path.read_bytes()


def test_round_trip_random_chunk(tmp_path):
    rng = np.random.default_rng(0)
    c = Chunk.empty(-1, 0, max_layers=8)
    sel = rng.random((10000, 8)) < 0.1
    c.cells["h"][sel] = rng.normal(30, 10, sel.sum())
    c.cells["n"][sel] = [0, 1, 0]
    c.cells["hits"][sel] = rng.integers(1, 65535, sel.sum())
    c.cells["flags"][sel] = FLAG_VALID
    c.cells["ts"][sel] = 1767225600
    write_chunk(tmp_path / "c.trn2", c)
    assert read_chunk(tmp_path / "c.trn2") == c


def test_bad_files_are_named(tmp_path):
    good = Chunk.empty(0, 0, 2).to_bytes()
    cases = {
        "magic.trn2": (b"TRN3" + good[4:], "bad magic"),
        "version.trn2": (good[:4] + struct.pack("<i", 3) + good[8:], "unsupported version 3"),
        "truncated.trn2": (good[:-7], "truncated"),
        "tiny.trn2": (good[:10], "truncated"),
    }
    for name, (data, msg) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(TerrainFormatError, match=msg) as ei:
            read_chunk(tmp_path / name)
        assert name in str(ei.value)
    nan_chunk = Chunk.empty(0, 0, 1)
    nan_chunk.cells["flags"][5, 0] = FLAG_VALID
    nan_chunk.cells["h"][5, 0] = np.nan
    (tmp_path / "nan.trn2").write_bytes(nan_chunk.to_bytes())
    with pytest.raises(TerrainFormatError, match="non-finite"):
        read_chunk(tmp_path / "nan.trn2")


def test_floor_indexing_for_negative_coordinates():
    assert chunk_of(-0.5, 0.5) == (-1, 0)
    gx, gz = cell_of(np.array([-0.5, -1.0, 0.0, -950.2]), np.array([850.7, 0.0, -1e-9, -100.0]))
    assert gx.tolist() == [-1, -1, 0, -951] and gz.tolist() == [850, 0, -1, -100]
    cx, cz, idx = split_cell(gx, gz)
    assert cx.tolist() == [-1, -1, 0, -10] and cz.tolist() == [8, 0, -1, -1]
    # cell -951 is column 49 of chunk -10 (x = -1000 + 49); row 50 of chunk 8 for z = 850
    assert idx[3] == 0 * 100 + 49 and idx[0] == 50 * 100 + 99
