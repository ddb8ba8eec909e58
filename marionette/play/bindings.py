"""What the page's keys play: each entity's tokens as actions (name, class, kind, clip length, how often the corpus
plays them) and the default key bindings (the most played tokens, attacks first)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from marionette.corpus import Corpus

KEYS = "1234567890JKLUIOHYTGBNMZXCVF"  # bindable keys: W A S D move, Q E turn, P pause, R restart are the page's own
CLASS_ORDER = ("attack", "other", "locomotion", "stationary")


@dataclass(frozen=True)
class Action:
    """One entity token as the page lists it: its name, class and kind from the corpus vocab, how long its clip
    plays (model frames) and how often the corpus plays it (source frames)."""

    entity: str
    token: int
    name: str
    cls: str
    kind: str
    clip_frames: int
    plays: int

    def to_json(self) -> dict:
        return {
            "entity": self.entity,
            "token": self.token,
            "name": self.name,
            "class": self.cls,
            "kind": self.kind,
            "clip_frames": self.clip_frames,
            "plays": self.plays,
        }


def action_table(corpus: Corpus, tokens, model_fps: float) -> dict[str, list[Action]]:
    """Per articulated entity, its tokens 1… with their vocab names and classes (token 0, "no valid action", is never
    forced)."""
    out: dict[str, list[Action]] = {}
    fields = {f: tokens.token_field(corpus.vocab, f) for f in ("name", "class", "kind", "frames", "bank", "motion")}
    ratio = corpus.fps / model_fps
    for i, e in enumerate(tokens.entities):
        rows = []
        for t in range(1, tokens.sizes[i]):
            type_key = tokens.type_keys[i][t]
            bank, motion = fields["bank"][i][t], fields["motion"][i][t]
            named = fields["name"][i][t] or (
                f"bank {bank} motion {motion}" if bank is not None else f"action {tokens.composites[i][t]}"
            )
            if len({k for k in tokens.type_keys[i][1:]}) > 1:
                named = f"{type_key} {named}"
            clip = int(np.ceil(tokens.clip_lengths[i][t] / ratio))
            rows.append(
                Action(
                    e,
                    t,
                    str(named),
                    str(fields["class"][i][t] or "other"),
                    str(fields["kind"][i][t] or ""),
                    max(clip, 1),
                    int(fields["frames"][i][t] or 0),
                )
            )
        out[e] = rows
    return out


def default_bindings(actions: list[Action]) -> dict[str, int]:
    """Key → token for one entity: its most played tokens (as many as ``KEYS``), attacks first, then other events,
    locomotion, stationary; most played first within a class."""
    best = sorted(actions, key=lambda a: (-a.plays, a.token))[: len(KEYS)]
    order = sorted(
        best, key=lambda a: (CLASS_ORDER.index(a.cls) if a.cls in CLASS_ORDER else len(CLASS_ORDER), -a.plays, a.token)
    )
    return {k: a.token for k, a in zip(KEYS, order)}
