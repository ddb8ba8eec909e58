"""The corpus viewer: recorded or generated state played through the bridge with no model, with a scrubber.

A ``ReplaySession`` plays one segment's rows — a corpus segment at its source rate, or a ``STATES.arrow`` (a
rollout, a play session) — at the rows' own rate. The skeletons are decoded once (``bridge.kinematics``, as
``marionette render`` does) and the follow camera is run over the whole segment once (``camera.follow_cameras``),
so a seek shows frame k exactly as a render of the segment shows it. Tokens are named from the corpus vocab when
a corpus is given (a table's action ids otherwise). The terrain is the segment's stage (for a table: the stage of
the corpus segment its rows were seeded from, found by the rows' ``sample``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from marionette.bridge.kinematics import world_skeletons
from marionette.bridge.targets import TerrainScene, chunk_inputs, follow_view
from marionette.corpus import MODEL_FPS, Corpus
from marionette.corpus.vocab import ActionTokens
from marionette.eval.control import tip_speeds
from marionette.io import read_ipc
from marionette.schema import layout_of_schema
from terrain_scan.store import stage_terrain

from .bindings import action_table
from .messages import int_field
from .playable import Playable
from .view import FrameView, stage_map


def replay_rows(source: Path, segment: str | None, corpus: Corpus | None) -> tuple[pa.Table, str, Corpus | None]:
    """(rows, segment id, corpus) of a replay: a corpus directory's segment (source rate), or a STATES.arrow's segment
    (its only one unless ``segment`` names one)."""
    source = Path(source)
    if source.is_dir():
        c = Corpus(source)
        if segment is None:
            raise ValueError(f"{source}: replaying a corpus needs --segment ID (`marionette inspect {source} --segments`)")
        if segment not in c.segment_ids():
            raise ValueError(f"{source}: no segment {segment!r} (`marionette inspect {source} --segments` lists them)")
        return c.read_segment(segment), segment, c
    if not source.is_file():
        raise ValueError(f"{source}: neither a corpus directory nor a STATES.arrow file")
    rows = read_ipc(source)
    ids = pc.unique(rows["segment"]).to_pylist() if "segment" in rows.column_names else []
    if not ids:
        raise ValueError(f"{source}: no rows to replay")
    if segment is None:
        if len(ids) > 1:
            raise ValueError(f"{source}: holds {len(ids)} segments ({', '.join(ids[:5])}…); name one with --segment")
        segment = ids[0]
    elif segment not in ids:
        raise ValueError(f"{source}: no segment {segment!r} (it holds {', '.join(ids[:10])})")
    return rows.filter(pc.equal(rows["segment"], segment)), segment, corpus


class ReplaySession(Playable):
    """Plays ``rows`` (one segment, corpus state schema) frame by frame with a scrubber (``seek``)."""

    kind = "replay"
    HANDLERS = ("pause", "step", "camera", "seek")

    def __init__(
        self,
        source: Path | str,
        *,
        segment: str | None = None,
        corpus: Corpus | Path | str | None = None,
        size: tuple[int, int] = (176, 320),
        paused: bool = False,
        log=print,
    ) -> None:
        super().__init__()
        c = corpus if isinstance(corpus, Corpus) or corpus is None else Corpus(Path(corpus))
        rows, self.segment, self.corpus = replay_rows(Path(source), segment, c)
        self.source, self.size, self.log = Path(source), tuple(size), log
        self.layout = layout_of_schema(rows.schema, str(source)) if self.corpus is None else self.corpus.layout
        if rows.num_rows < 1:
            raise ValueError(f"{source}: segment {self.segment} has no rows")
        state, anchors, valid, t = chunk_inputs(self.layout, rows)
        if len(t) > 1 and not np.all(np.diff(t) > 0):
            raise ValueError(f"{source}: segment {self.segment}'s times are not increasing")
        self.fps = float(round(1.0 / float(np.median(np.diff(t))), 6)) if len(t) > 1 else MODEL_FPS
        self.skel = world_skeletons(self.layout, state, anchors, valid, t)
        self.times = t
        self.n = rows.num_rows
        self.paused = bool(paused)
        self.frame = 0
        self._seek: int | None = 0
        self.stage = self._stage(rows)
        self.terrain = TerrainScene.of_stage(stage_terrain(self.corpus.path, self.stage)) if self.stage else TerrainScene.empty()
        self._map = stage_map(self.terrain)
        self.cams = follow_view(self.layout, self.skel, self.fps, self.size[1], self.size[0])
        self.tips = {
            e.owner: np.r_[0.0, tip_speeds(self.layout, state.astype(np.float64), self.fps, e.name)]
            for e in self.layout.attachments
        }
        self.tokens = self._names(rows)

    def _stage(self, rows: pa.Table) -> str | None:
        """The stage of the rows: their corpus segment's, else that of a corpus segment of the same sample."""
        if self.corpus is None:
            return None
        segs = self.corpus.segments
        if self.segment in segs["segment"].to_pylist():
            return self.corpus.stage_of(self.segment)
        sample = rows["sample"][0].as_py()
        same = segs.filter(pc.equal(segs["sample"], sample))
        return same["stage"][0].as_py() if same.num_rows else None

    def _names(self, rows: pa.Table) -> dict[str, list[tuple[int, str, str]]]:
        """Per articulated entity, per row: (token or composite action id, name, class)."""
        out = {}
        if self.corpus is not None:
            tokens = ActionTokens.from_corpus(self.corpus)
            toks = tokens.encode(self.layout, rows, where=str(self.source))[0]
            table = action_table(self.corpus, tokens, self.fps)
            for i, e in enumerate(tokens.entities):
                acts = table[e]
                out[e] = [
                    (int(k), acts[k - 1].name, acts[k - 1].cls) if k > 0 else (0, "no valid action", "none") for k in toks[:, i]
                ]
            return out
        for e in self.layout.articulated:
            ids = rows[f"{e.name}.action"].to_numpy()
            out[e.name] = [(int(a), f"action {int(a)}", "") for a in ids]
        return out

    def seek(self, frame: Any) -> dict:
        """Show ``frame`` (0 … n − 1) next."""
        k = int_field({"frame": frame}, "frame", 0, self.n - 1)
        with self.lock:
            self._seek = k
        return {"frame": k, "frames": self.n}

    def _on_seek(self, m: dict) -> dict:
        return self.seek(m.get("frame"))

    def advance(self) -> tuple[dict, np.ndarray] | None:
        """The next frame (or the one a seek asked for); at the last frame the replay pauses."""
        with self.lock:
            if self._seek is not None:
                self.frame, self._seek = self._seek, None
            elif self.frame + 1 >= self.n:
                self.paused = True
                self._steps = 0
                return None
            elif self._may_step():
                self.frame += 1
            else:
                return None
            if self.view is None:
                roots_y = np.concatenate([self.skel.joints[e.name][:, 0, 1] for e in self.layout.articulated])
                self.view = FrameView(self.layout, self.terrain, self.size, self.fps, roots_y)
            k = self.frame
            world = {n: j[k] for n, j in self.skel.joints.items()}
            rot = {n: r[k] for n, r in self.skel.rot.items()}
            self._pixels = (
                self.view.render_with(self.cams, k, world)
                if self.camera_mode == "follow"
                else self.view.render(world, rot, self.camera_mode, self.orbit)
            )
            self._last = self._meta(k, world, rot)
            return self._last, self._pixels

    def _meta(self, k: int, world: dict, rot: dict) -> dict:
        ents = {}
        for e in self.layout.articulated:
            tok, name, cls = self.tokens[e.name][k]
            f = rot[e.name] @ np.asarray(e.rig.forward_axis, np.float64)
            ents[e.name] = {
                "token": tok,
                "name": name,
                "class": cls,
                "root": [round(float(x), 3) for x in world[e.name][0]],
                "heading": round(float(np.degrees(np.arctan2(f[0], f[2]))), 1),
                "valid": bool(self.skel.valid[e.name][k]),
            }
            if e.name in self.tips:
                ents[e.name]["tip_speed"] = round(float(self.tips[e.name][k]), 3)
        return {
            "type": "frame",
            "kind": self.kind,
            "frame": k,
            "frames": self.n,
            "t": float(self.times[k]),
            "entities": ents,
            "width": self.size[1],
            "height": self.size[0],
        }

    def status(self) -> dict:
        with self.lock:
            return {
                "kind": self.kind,
                "source": str(self.source),
                "segment": self.segment,
                "frame": self.frame,
                "frames": self.n,
                "paused": self.paused,
                "fps": self.fps,
                "stage": self.stage,
                "entities": None if self._last is None else self._last["entities"],
                "camera": {"mode": self.camera_mode, **vars(self.orbit)},
                "size": list(self.size),
            }
