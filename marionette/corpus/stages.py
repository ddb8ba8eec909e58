"""Which stage each recording plays on: ``meta/stages.json``.

WildWorld's ``state.csv`` names no stage. A source tree may carry ``stages.json`` (recording → stage, the
user's word, which always wins); every other recording is placed by the terrain scan, which groups
recordings by the agreement of their scanned terrain (``terrain_scan.grouping``) and writes the whole
placement here: ``{"recordings": {"part/id": "stage"}, "found": {"part/id": {"stage": ..., "scan": key}}}`` —
``found`` is what the grouping decided and with which scan options. A user may edit ``recordings`` (move a
recording, split or rename a stage); the next scan applies the edit, and never undoes it. A placement the
grouping found with other scan options (a new depth decoder: the terrain it compared was another) is made
again by the next scan. A recording listed nowhere reads as stage ``default`` until a scan places it.
"""

from __future__ import annotations

from pathlib import Path

from marionette.corpus.paths import ID_PATTERN, meta
from marionette.io import read_json, write_json

STAGES_FILE = "stages.json"
MAX_STAGES_BYTES = 64 << 20
UNPLACED = "default"


def is_recording_id(rec: object) -> bool:
    """Whether ``rec`` is a recording id: ``part/id``, two directory names (never a path: no further ``/``, no NUL,
    neither ``.`` nor ``..``, each within the file system's 255 bytes)."""
    if not isinstance(rec, str) or rec.count("/") != 1 or "\0" in rec:
        return False
    return all(n not in ("", ".", "..") and len(n.encode("utf-8", "surrogatepass")) <= 255 for n in rec.split("/"))


def check_stage_map(d: object, where: str) -> dict[str, str]:
    """A source tree's ``stages.json`` (recording id → stage id), checked: an object of recording ids to stage ids
    (``ID_PATTERN``, so that two stages never share one directory)."""
    if not isinstance(d, dict):
        raise ValueError(f'{where}: not an object of recording id → stage id ({{"part/id": "stage"}})')
    for rec, stage in d.items():
        if not is_recording_id(rec):
            raise ValueError(f"{where}: {rec!r} is not a recording id (part/id)")
        if not isinstance(stage, str) or not ID_PATTERN.fullmatch(stage):
            raise ValueError(f"{where}: recording {rec!r}: stage {stage!r} is not an id ([A-Za-z0-9_-], at most 200)")
    return dict(d)


def _check(d: object, where: str, field: str = "recordings") -> dict[str, str]:
    if not isinstance(d, dict) or not isinstance(d.get(field), dict):
        raise ValueError(f'{where}: not a stage placement (an object {{"recordings": {{"part/id": "stage"}}}})')
    out = {}
    for rec, stage in d[field].items():
        if field == "found":
            if not isinstance(stage, dict) or not isinstance(stage.get("scan"), str):
                raise ValueError(f"{where}: found[{rec!r}] is not {{'stage': ..., 'scan': key}}")
            stage = stage.get("stage")
        if not is_recording_id(rec):
            raise ValueError(f"{where}: {rec!r} is not a recording id (part/id)")
        if not isinstance(stage, str) or not ID_PATTERN.fullmatch(stage):
            raise ValueError(f"{where}: recording {rec!r}: stage {stage!r} is not an id ([A-Za-z0-9_-], at most 200)")
        out[rec] = stage
    return out


def read_placements(corpus: Path) -> dict[str, str]:
    """``meta/stages.json`` of a corpus (recording → stage), checked; {} when there is none."""
    return read_stage_file(corpus)[0]


def read_stage_file(corpus: Path) -> tuple[dict[str, str], dict[str, dict]]:
    """``meta/stages.json``: (recording → stage, recording → what the grouping found {"stage", "scan"}), checked."""
    path = meta(corpus, STAGES_FILE)
    if not path.exists():
        return {}, {}
    d = read_json(path, MAX_STAGES_BYTES)
    placed = _check(d, str(path))
    found = {}
    if "found" in d:
        _check(d, str(path), "found")
        found = {rec: {"stage": v["stage"], "scan": v["scan"]} for rec, v in d["found"].items()}
    return placed, found


def write_placements(corpus: Path, placements: dict[str, str], found: dict[str, dict] | None = None) -> Path:
    """Write ``meta/stages.json`` atomically (sorted), returning its path."""
    path = meta(corpus, STAGES_FILE)
    write_json(path, {"recordings": dict(sorted(placements.items())), "found": dict(sorted((found or {}).items()))})
    return path
