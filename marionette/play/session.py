"""A live rollout a person drives: the dynamics model stepped in real time, its frames rendered through the bridge.

``LiveSession`` owns one ``dynamics.engine.Rollout`` (batch 1) seeded from a corpus segment, and per frame:

1. takes the controls that arrived since the last frame (``control``): a token forced on an entity for a number of
   frames (a key press forces its bound token for the action's clip, so an attack plays out), a root velocity in the
   entity's own frame (m/s, the rollout's root script; WASD) with an optional turn (degrees/s about the vertical);
2. steps the rollout with them (the rules in the loop as switched: ``set_rules``);
3. renders the corrected frame through the bridge (``view.FrameView``: follow or orbit camera) and reports each
   entity's token (with its name and class), roots, weapon-tip speed and the control it answers (``ack``).

A fresh key press on the token an entity already plays replays it from its start (the rollout's ``restart``); a
press while a window of the same token is still forced extends it. Everything a frame used is kept (up to
``MAX_HISTORY`` frames since the last reset), so ``record`` can write the frames since recording started as a
corpus-schema ``STATES.arrow`` and a G-buffer ``.mkv`` of them (``recording``). Recordings go under the session's
recording directory with names the session makes or checks (``messages.checked_name``). The key bindings are
``bindings``'s; the page's other messages (pause, steps, camera) are ``playable.Playable``'s.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from marionette import geometry as geo
from marionette.bridge.camera import recorded_cameras
from marionette.bridge.gbuffer import to_codes
from marionette.bridge.rules import RULES, enabled_rules
from marionette.bridge.targets import TerrainScene, source_size
from marionette.checkpoint import read_meta
from marionette.corpus import Corpus, as_corpus, fixed_rows
from marionette.dynamics.engine import Rollout, checkpoint_dir, open_terrain_field
from marionette.dynamics.rollout import rollout_table
from marionette.eval.control import tip_speeds
from marionette.video import CropResize
from terrain_scan.store import segment_terrain

from .bindings import KEYS, action_table, default_bindings
from .messages import MAX_CONTROL_FRAMES, checked_name, checked_root, checked_turn, int_field
from .playable import Playable
from .recording import MAX_HISTORY, History, free_name, name_taken, write_recording
from .view import FrameView, stage_map


@dataclass
class _Forced:
    token: int
    frames: int  # frames left
    fresh: bool  # replay the action from its start on the next frame
    seq: int


@dataclass
class _Move:
    velocity: np.ndarray  # (3,) m/s, entity's own frame; NaN = the model's
    turn: float  # degrees/s about the vertical
    frames: float  # frames left (inf: until the next move)
    seq: int


class LiveSession(Playable):
    """A playable rollout of ``ckpt`` on ``corpus`` (module doc). Thread-safe: the server's loop calls ``advance``,
    request handlers call ``control``, ``reset``, ``record``, ``set_rules``, ``status``."""

    kind = "live"

    def __init__(
        self,
        ckpt: Path | str,
        corpus: Corpus | Path | str,
        *,
        segment: str | None = None,
        seed_frames: int = 64,
        size: tuple[int, int] = (176, 320),
        temperature: float = 0.0,
        seed: int = 0,
        rules: str = "auto",
        record_dir: Path | str = "play-sessions",
        paused: bool = False,
        observation: Path | str | None = None,
        paint_steps: int = 4,
        log=print,
    ) -> None:
        trained = read_meta(checkpoint_dir(ckpt))["train_config"]
        self.corpus = as_corpus(corpus, trained.get("scene"))
        self.layout = self.corpus.layout
        self.seed_frames, self.size, self.seed = int(seed_frames), tuple(size), int(seed)
        self.record_dir = Path(record_dir)
        self.log = log
        super().__init__()
        self.controls_lock = threading.RLock()  # the controls' own: taken between frames and by requests, briefly
        self.ro = Rollout(ckpt, self.corpus, temperature=temperature, seed=seed, rules="none")
        self.fps = self.ro.fps
        self.names = [e.name for e in self.layout.articulated]
        self.actions = action_table(self.corpus, self.ro.tokens, self.fps)
        self.driven = "hunter" if "hunter" in self.names else self.names[0]
        self.bindings = {e: default_bindings(self.actions[e]) for e in self.names}
        self.rules_asked = rules
        self.terrain: TerrainScene | None = None
        self.stage: str | None = None
        self._forced: dict[int, _Forced] = {}
        self._moves: dict[int, _Move] = {}
        self._seq = 0
        self.recording: dict | None = None
        self.written: list[dict] = []
        self.paused = bool(paused)
        self.frame, self.segment, self.start = 0, None, 0
        self._pending: tuple | None = None
        self.painter = None
        if observation is not None:
            from .painter import Painter

            self.painter = Painter(Path(observation), self.size, paint_steps, seed, log)
            self.observation = Path(observation)
        self.reset(segment or self.default_segment())

    # -- the scene ---------------------------------------------------------------------------------

    def default_segment(self) -> str:
        """The longest held-out segment (else the longest) that holds the seed."""
        test = self.corpus.segment_ids("test") or self.corpus.segment_ids()
        return max(test, key=lambda s: self.corpus.dynamics_segment(s, self.fps).num_rows)

    def segments(self) -> list[str]:
        """Segments long enough to seed a session."""
        seg = self.corpus.segments  # one read of the table, not one per segment
        return [s for s, n in zip(seg["segment"].to_pylist(), seg["frames"].to_pylist()) if n > 0]

    def reset(self, segment: str | None = None, start: int = 0, paused: bool | None = None) -> dict:
        """Seed the rollout again from ``segment`` (default: the current one) at dynamics frame ``start``; checked now,
        done by the loop before its next frame (the thread that renders owns the GL context)."""
        segment = segment or self.segment
        if segment not in self.corpus.segment_ids():
            raise ValueError(f"{self.corpus.path}: no segment {segment!r} (`marionette inspect CORPUS --segments` lists them)")
        if isinstance(start, bool) or not isinstance(start, int):
            raise ValueError(f"start {start!r} is not an integer")
        view = self.corpus.dynamics_segment(segment, self.fps)
        n = view.num_rows
        if start < 0 or n < start + self.seed_frames:
            raise ValueError(
                f"segment {segment} has {n} dynamics frames; a {self.seed_frames}-frame seed from frame {start} does not fit"
            )
        if paused is not None and not isinstance(paused, bool):
            raise ValueError(f"paused is true or false, not {paused!r}")
        with self.lock:
            self._pending = (segment, view, int(start), paused)
        return {"segment": segment, "start": int(start), "pending": True}

    def _reset_now(self, segment: str, view: pa.Table, start: int, paused: bool | None) -> None:
        stage = self.corpus.stage_of(segment)
        first = self.view is None
        if stage != self.stage:  # the terrain (collider, render, map) of the new stage
            self.ro.field = open_terrain_field(self.corpus, segment)
            self.terrain = TerrainScene.of_stage(segment_terrain(self.corpus, segment))
            self.stage = stage
            self._map = stage_map(self.terrain)
            if self.view is not None:
                self.view.release()
                self.view = None
        self.segment, self.start = segment, int(start)
        self.seed_rows = view.slice(start, self.seed_frames)
        self.ro.enabled = self._rules_from(self.rules_asked if first else self.ro.enabled)
        self.ro.start(self.seed_rows)
        if self.view is None:
            roots_y = np.concatenate(
                [fixed_rows(self.seed_rows[f"{e.name}.root_world"], 3)[:, 1] for e in self.layout.articulated]
            )
            self.view = FrameView(self.layout, self.terrain, self.size, self.fps, roots_y)
        last = self.seed_rows.slice(self.seed_rows.num_rows - 1, 1)
        self.view.reset_camera(self._recorded_camera(segment, last) if self.painter is not None else None)
        self.history = History()
        with self.controls_lock:
            self._forced, self._moves = {}, {}
            self._ack = self._seq
        self.recording = None
        self.frame = 0
        self._prev_state = np.asarray(self.ro.state, np.float32)
        if paused is not None:
            self.paused = paused
        self._steps = 0
        self._pixels = self.view.render(self.ro.world, self._rotations(), self.camera_mode, self.orbit)
        self._last = self._frame_meta(np.zeros(len(self.layout.attachments)))
        if self.painter is not None:
            from .painter import recorded_frame

            self.painter.start_scene(
                recorded_frame(self.corpus, segment, int(last["frame"][0].as_py())), to_codes(self.view.last_float)
            )
        self.log(f"play: seeded from {segment} frames {start}..{start + self.seed_frames - 1} on stage {stage}")

    def _recorded_camera(self, segment: str, row: pa.Table):
        """The recorded camera of one corpus row at the view's size (the video chunks' centred crop), or None if the
        row's camera is not valid: where a painted session's follow camera starts, so that its first pose frame shows
        what the recorded first RGB frame shows."""

        H, W = self.size
        src_h, src_w = source_size(self.corpus, segment)
        cams = recorded_cameras(
            fixed_rows(row["camera.K"], 4),
            fixed_rows(row["camera.pos"], 3),
            fixed_rows(row["camera.rot"], 4),
            np.ones(1, bool),
            W,
            H,
            crop=CropResize.fit(src_h, src_w, H, W),
        )
        return cams if cams.valid[0] else None

    def _rules_from(self, asked) -> tuple[str, ...]:

        possible = enabled_rules(self.layout, self.ro.field)
        if asked == "auto":
            return possible
        if asked in ("none", None):
            return ()
        asked = tuple(asked.split(",")) if isinstance(asked, str) else tuple(asked)
        return tuple(r for r in asked if r in possible)

    def set_rules(self, wanted: dict) -> dict:
        """Switch rules: {"collider": bool, "cap": bool} (either may be left out)."""
        if not isinstance(wanted, dict) or set(wanted) - set(RULES) or not all(isinstance(v, bool) for v in wanted.values()):
            raise ValueError(f"rules: expected an object of {list(RULES)} → true/false, not {wanted!r}")
        with self.lock:
            now = set(self.ro.enabled)
            now |= {r for r, on in wanted.items() if on}
            now -= {r for r, on in wanted.items() if not on}
            self.ro.set_rules(tuple(now))
            return self.rules()

    def rules(self) -> dict:

        possible = enabled_rules(self.layout, self.ro.field)
        return {r: {"on": r in self.ro.enabled, "available": r in possible} for r in RULES}

    def _rotations(self) -> dict[str, np.ndarray]:
        R = geo.quat_to_matrix(np.asarray(self.ro.quats, np.float64))
        return {n: R[i] for i, n in enumerate(self.names)}

    # -- controls ----------------------------------------------------------------------------------

    def entity_index(self, entity: Any) -> int:
        if entity not in self.names:
            raise ValueError(f"unknown entity {entity!r}; the scene has {self.names}")
        return self.names.index(entity)

    def control(self, msg: dict) -> dict:
        """{"entity", "token"[, "frames"]} forces a token (default: for its clip); {"entity", "root": [vx, vy, vz]
        (m/s, own frame; null = the model's)[, "turn": deg/s][, "frames"]} moves the root (default 20 frames; "frames":
        0 holds it until the next root control). A bad entity, token, velocity or frame count is a ValueError naming it."""
        if not isinstance(msg, dict):
            raise ValueError(f"a control is a JSON object, not {type(msg).__name__}")
        if unknown := set(msg) - {"entity", "token", "root", "turn", "frames", "seq", "type"}:
            raise ValueError(f"unknown control fields {sorted(unknown)}")
        entity = msg.get("entity", self.driven)
        i = self.entity_index(entity)
        if "token" not in msg and "root" not in msg:
            raise ValueError("a control gives a token or a root velocity")
        with self.controls_lock:  # never the step's lock: a control is taken while a frame is made
            self._seq += 1
            seq = self._seq
            if "token" in msg:
                tok = msg["token"]
                size = self.ro.tokens.sizes[i]
                if isinstance(tok, bool) or not isinstance(tok, int) or not 1 <= tok < size:
                    raise ValueError(f"token {tok!r} is not one of {entity}'s tokens 1..{size - 1} (0 is 'no valid action')")
                clip = self.actions[entity][tok - 1].clip_frames
                frames = int_field(msg, "frames", 1, MAX_CONTROL_FRAMES, clip)
                held = self._forced.get(i)
                if held is not None and held.token == tok and held.frames > 0:
                    held.frames, held.seq = max(held.frames, frames), seq  # still playing: it goes on
                else:
                    self._forced[i] = _Forced(tok, frames, True, seq)
            if "root" in msg:
                vel, turn = checked_root(msg["root"]), checked_turn(msg.get("turn", 0.0))
                frames = int_field(msg, "frames", 0, MAX_CONTROL_FRAMES, 20)
                self._moves[i] = _Move(vel, turn, np.inf if frames == 0 else frames, seq)
            return {"entity": entity, "seq": seq, "from_frame": self.frame + 1}

    def move(self, entity: str, forward: float, right: float, turn: float) -> dict:
        """WASD: a velocity (m/s) along the entity's forward axis and to its right, and a turn (degrees/s, positive to
        the left), held until the next ``move``; all zero hands the root back to the model."""
        i = self.entity_index(entity)
        if not all(isinstance(x, int | float) and not isinstance(x, bool) for x in (forward, right, turn)):
            raise ValueError("move: forward, right and turn are numbers")
        rig = self.layout.articulated[i].rig
        fwd = np.asarray(rig.forward_axis, np.float64)
        left = np.cross([0.0, 1.0, 0.0], fwd)
        with self.controls_lock:  # never the step's lock: a control is taken while a frame is made
            if forward == 0 and right == 0 and turn == 0:
                self._moves.pop(i, None)
                self._seq += 1
                return {"entity": entity, "seq": self._seq, "from_frame": self.frame + 1}
            v = forward * fwd - right * left
            v[1] = np.nan  # the model's vertical motion (jumps, slopes)
            return self.control(
                {"entity": entity, "root": [None if np.isnan(x) else float(x) for x in v], "turn": turn, "frames": 0}
            )

    def bind(self, entity: str, key: str, token: int | None) -> dict:
        """Bind ``key`` to an entity's token (None: unbind)."""
        self.entity_index(entity)
        if not isinstance(key, str) or len(key) != 1 or key.upper() not in KEYS:
            raise ValueError(f"key {key!r} is not one of the bindable keys {KEYS}")
        with self.lock:
            b = self.bindings[entity]
            if token is None:
                b.pop(key.upper(), None)
            else:
                size = self.ro.tokens.sizes[self.names.index(entity)]
                if isinstance(token, bool) or not isinstance(token, int) or not 1 <= token < size:
                    raise ValueError(f"token {token!r} is not one of {entity}'s tokens 1..{size - 1}")
                b[key.upper()] = token
            return {"entity": entity, "bindings": dict(b)}

    def drive(self, entity: str) -> dict:
        """Which entity the keys drive (the other goes on freely)."""
        self.entity_index(entity)
        with self.lock:
            self.driven = entity
        return {"driven": entity}

    def _step_controls(self) -> tuple[dict[int, int], np.ndarray | None, list[int], int]:
        """This frame's forced tokens, root override (root stream, state units), replayed entities and the newest
        control it answers; counts the windows down."""
        with self.controls_lock:
            return self._take_controls()

    def _take_controls(self) -> tuple[dict[int, int], np.ndarray | None, list[int], int]:
        forced, restart, ack = {}, [], self._ack
        for i, f in list(self._forced.items()):
            forced[i] = f.token
            if f.fresh:
                restart.append(i)
                f.fresh = False
            ack = max(ack, f.seq)
            f.frames -= 1
            if f.frames <= 0:
                del self._forced[i]
        override = None
        for i, m in list(self._moves.items()):
            if override is None:
                override = np.full(self.ro.config.root_dim, np.nan)
            override[9 * i : 9 * i + 3] = m.velocity / self.fps
            if m.turn:
                R = geo.quat_to_matrix(np.asarray(self.ro.quats[i], np.float64))
                yaw = np.radians(m.turn) / self.fps
                c, s = np.cos(yaw), np.sin(yaw)
                turned = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]) @ R
                override[9 * i + 3 : 9 * i + 9] = geo.matrix_to_rot6d(turned)
            ack = max(ack, m.seq)
            m.frames -= 1
            if m.frames <= 0:
                del self._moves[i]
        return forced, override, restart, ack

    # -- the loop ----------------------------------------------------------------------------------

    def advance(self) -> tuple[dict, np.ndarray] | None:
        """One frame (its meta and G-buffer pixels), or None while paused with no single steps queued; a pending
        reset gives the seed's last frame (frame 0)."""
        with self.lock:
            if self._pending is not None:
                pending, self._pending = self._pending, None
                self._reset_now(*pending)
                return self._last, self._pixels
            if not self._may_step():
                return None
            t0 = time.perf_counter()
            forced, override, restart, ack = self._step_controls()
            state = self.ro.step(forced, override, restart)
            stepped = time.perf_counter()
            self.history.add(self.ro, state)
            self.frame += 1
            self._ack = ack
            tips = self._tips(state)
            self._prev_state = np.asarray(state, np.float32)
            self._pixels = self.view.render(self.ro.world, self._rotations(), self.camera_mode, self.orbit)
            if self.painter is not None:
                self.painter.feed(self.frame, self.view.last_float)
            done = time.perf_counter()
            self._last = self._frame_meta(tips, step_ms=1e3 * (stepped - t0), render_ms=1e3 * (done - stepped))
            return self._last, self._pixels

    def _tips(self, state: np.ndarray) -> np.ndarray:
        both = np.stack([self._prev_state, np.asarray(state, np.float32)])
        return np.array([float(tip_speeds(self.layout, both, self.fps, e.name)[0]) for e in self.layout.attachments])

    def _frame_meta(self, tips: np.ndarray, step_ms: float = 0.0, render_ms: float = 0.0) -> dict:
        ents = {}
        for i, n in enumerate(self.names):
            tok = int(self.ro.tok[i])
            a = self.actions[n][tok - 1] if tok > 0 else None
            ents[n] = {
                "token": tok,
                "name": a.name if a else "no valid action",
                "class": a.cls if a else "none",
                "forced": i in self._forced,
                "moved": i in self._moves,
                "root": [round(float(x), 3) for x in self.ro.roots_world[i]],
                "heading": round(float(np.degrees(np.arctan2(*self._heading(i)))), 1),
            }
        for e, s in zip(self.layout.attachments, tips):
            ents[e.owner]["tip_speed"] = round(float(s), 3)
        return {
            "type": "frame",
            "kind": self.kind,
            "frame": self.frame,
            "ack": self._ack,
            "entities": ents,
            "step_ms": round(step_ms, 2),
            "render_ms": round(render_ms, 2),
            "width": self.size[1],
            "height": self.size[0],
            "recording": self.recording is not None,
        }

    def _heading(self, i: int) -> tuple[float, float]:
        R = geo.quat_to_matrix(np.asarray(self.ro.quats[i], np.float64))
        f = R @ np.asarray(self.layout.articulated[i].rig.forward_axis, np.float64)
        return float(f[0]), float(f[2])

    def status(self) -> dict:
        with self.lock:
            return {
                "kind": self.kind,
                "frame": self.frame,
                "paused": self.paused,
                "segment": self.segment,
                "start": self.start,
                "stage": self.stage,
                "fps": self.fps,
                "driven": self.driven,
                "entities": None if self._last is None else self._last["entities"],
                "rules": self.rules(),
                "camera": {"mode": self.camera_mode, **vars(self.orbit)},
                "recording": None
                if self.recording is None
                else {"name": self.recording["name"], "frames": self.frame - self.recording["from"]},
                "written": list(self.written),
                "size": list(self.size),
                "painting": None
                if self.painter is None
                else {
                    "model": str(self.observation),
                    "size": list(self.painter.size),
                    "fps": self.painter.painted_fps,
                    "error": self.painter.error,
                },
            }

    HANDLERS = ("pause", "step", "camera", "control", "move", "bind", "drive", "reset", "rules", "record")

    def close(self) -> None:
        if self.painter is not None:
            self.painter.close()
        super().close()

    def _on_control(self, m: dict) -> dict:
        return self.control(m)

    def _on_move(self, m: dict) -> dict:
        return self.move(m.get("entity", self.driven), m.get("forward", 0.0), m.get("right", 0.0), m.get("turn", 0.0))

    def _on_bind(self, m: dict) -> dict:
        return self.bind(m.get("entity", self.driven), m.get("key"), m.get("token"))

    def _on_drive(self, m: dict) -> dict:
        return self.drive(m.get("entity"))

    def _on_reset(self, m: dict) -> dict:
        return self.reset(m.get("segment"), m.get("start", 0), m.get("paused"))

    def _on_rules(self, m: dict) -> dict:
        return self.set_rules(m)

    def _on_record(self, m: dict) -> dict:
        return self.record(m)

    # -- recording ---------------------------------------------------------------------------------

    def record(self, msg: dict) -> dict:
        """{"action": "start"[, "name"]} or {"action": "stop"}: the frames from start to stop are written to
        ``<record_dir>/<name>.arrow`` and ``<name>.mkv`` (in the background; ``status()["written"]`` lists them)."""
        action = msg.get("action")
        with self.lock:
            if action == "start":
                if self.recording is not None:
                    raise ValueError(f"already recording {self.recording['name']!r}")
                name = checked_name(msg.get("name") or free_name(self.record_dir, self.written))
                if name_taken(self.record_dir, self.written, name):
                    raise FileExistsError(f"recording {name!r} exists in {self.record_dir}; choose another name")
                self.recording = {"name": name, "from": self.frame}
                return {"recording": name, "from_frame": self.frame}
            if action == "stop":
                if self.recording is None:
                    raise ValueError("not recording")
                rec, self.recording = self.recording, None
                first = len(self.history) - (self.frame - rec["from"])
                if first < 0:
                    raise ValueError(f"the recording's first frames are no longer kept (at most {MAX_HISTORY} frames)")
                if self.frame == rec["from"]:
                    raise ValueError("nothing recorded: no frame was played since recording started")
                table = self._table(first, rec["name"])
                out = {
                    "name": rec["name"],
                    "arrow": str(self.record_dir / f"{rec['name']}.arrow"),
                    "mkv": str(self.record_dir / f"{rec['name']}.mkv"),
                    "frames": table.num_rows,
                    "done": False,
                }
                self.written.append(out)
                args = (table, out, self.record_dir, self.layout, self.terrain, self.size, self.log)
                threading.Thread(target=write_recording, args=args, daemon=True).start()
                return out
        raise ValueError(f"record: action {action!r} is not 'start' or 'stop'")

    def _table(self, first: int, name: str) -> pa.Table:
        """The kept frames from ``first`` on as a corpus-schema table: the frame before ``first`` (a seed row, or a
        played one) first, then the played frames."""
        h = self.history
        sl = lambda d: np.array(list(d)[first:])  # noqa: E731
        # the row before the first recorded frame: the seed's last row, or a played frame (row ``first`` of the whole)
        seed = self.seed_rows.slice(self.seed_rows.num_rows - 1, 1) if first == 0 else self._table(0, name).slice(first, 1)
        return rollout_table(
            self.corpus,
            self.ro,
            seed,
            self.segment,
            self.seed,
            sl(h.states),
            sl(h.roots),
            sl(h.quats),
            sl(h.tokens),
            sl(h.progress),
            name=f"{self.segment}-play-{name}",
        )
