"""The action vocabulary: how a corpus names what its characters do.

``meta/vocab.json`` (written by ``marionette.ingest.finalize.build_vocab``) numbers the composite action
ids (bank × 1000 + motion + 1; 0 = no valid action) densely per entity type ``<rig>:<type_id>``, with
each action's clip length, kind (state: loops; event: plays once) and class. This module owns the class
rule (``classify``) and the entity token tables the models use (``ActionTokens``; the numbering is
described in ``marionette.dynamics.data``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import pyarrow as pa

from marionette.corpus import Corpus
from marionette.schema import Entity, Layout

# Action classes from motion statistics (per played instance, medians over instances):
# attack      — the peak root-frame speed of any joint or owned attachment point ≥ ATTACK_PEAK_MPS;
# locomotion  — a looping (state) action whose mean horizontal root speed ≥ LOCOMOTION_MPS;
# stationary  — a looping action below that speed;
# other       — an event that is not an attack (dodge, roar, ...).
ATTACK_PEAK_MPS = 7.0
LOCOMOTION_MPS = 0.5


def classify(kind: str, instances: list[list[float]]) -> str:
    """Action class from per-instance [mean root speed, peak body speed, frames]."""
    if not instances:
        return "other"
    arr = np.asarray(instances, np.float64)
    if np.median(arr[:, 1]) >= ATTACK_PEAK_MPS:
        return "attack"
    if kind == "state":
        return "locomotion" if np.median(arr[:, 0]) >= LOCOMOTION_MPS else "stationary"
    return "other"


MOTION_CLASSES = ("stationary", "locomotion", "attack", "other")  # a token's class index is 1 + its place here


def entity_type_key(entity: Entity, type_id: int) -> str:
    """The vocab.json key of an entity's type: ``<rig>:<type_id>``."""
    return f"{entity.rig.name}:{int(type_id)}"


@dataclass(frozen=True, eq=False)
class ActionTokens:
    """Per articulated entity (layout order): composite action ids → entity tokens, and each token's
    type, vocab token, composite id and clip length (module doc: the numbering)."""

    entities: tuple[str, ...]
    sizes: tuple[int, ...]
    vocab_hash: str
    lookup: tuple[dict[tuple[int, int], int], ...]  # per entity: (type_id, composite) → entity token
    type_keys: tuple[tuple[str, ...], ...]  # per entity, per token: "<rig>:<type_id>" ("" for token 0)
    vocab_tokens: tuple[np.ndarray, ...]  # per entity, per token: the token within its type's vocab
    composites: tuple[np.ndarray, ...]  # per entity, per token: composite id
    clip_lengths: tuple[np.ndarray, ...]  # per entity, per token: clip length, source frames (1 for token 0)
    # the corpus's source rate: with it, a resampled row's progress counts the time past its source frame (``encode``)
    source_fps: float = 0.0

    @classmethod
    def from_vocab(cls, vocab: dict, layout: Layout, source_fps: float = 0.0) -> ActionTokens:
        """Entity token tables from a corpus's vocab.json contents (``source_fps``: the corpus's rate, 0 if unknown)."""
        types = vocab.get("entity_types", {})
        lookup, keys, vtok, comp, clip, sizes = [], [], [], [], [], []
        for e in layout.articulated:
            mine = sorted((int(k.split(":", 1)[1]), k) for k in types if k.split(":", 1)[0] == e.rig.name)
            table: dict[tuple[int, int], int] = {}
            k_, v_, c_, l_ = [""], [0], [0], [1.0]
            for type_id, key in mine:
                for a in sorted(types[key]["actions"], key=lambda a: a["token"]):
                    if a["token"] == 0:
                        continue
                    table[(type_id, int(a["composite"]))] = len(k_)
                    k_.append(key)
                    v_.append(int(a["token"]))
                    c_.append(int(a["composite"]))
                    l_.append(float(max(int(a["clip_length"]), 1)))
            lookup.append(table)
            keys.append(tuple(k_))
            vtok.append(np.asarray(v_, np.int64))
            comp.append(np.asarray(c_, np.int64))
            clip.append(np.asarray(l_, np.float64))
            sizes.append(len(k_))
        return cls(
            tuple(e.name for e in layout.articulated),
            tuple(sizes),
            str(vocab.get("hash", "")),
            tuple(lookup),
            tuple(keys),
            tuple(vtok),
            tuple(comp),
            tuple(clip),
            float(source_fps),
        )

    def token_field(self, vocab: dict, field: str) -> tuple[tuple[Any, ...], ...]:
        """Per entity, per token: ``field`` of its action in a vocab.json's contents (None for token 0 and where the
        action lacks it)."""
        types = vocab.get("entity_types", {})
        by_token = {key: {int(a["token"]): a for a in t["actions"]} for key, t in types.items()}
        return tuple(
            (
                None,
                *(by_token[key].get(int(vt), {}).get(field) for key, vt in zip(self.type_keys[i][1:], self.vocab_tokens[i][1:])),
            )
            for i in range(len(self.entities))
        )

    def event_lengths(self, vocab: dict) -> tuple[tuple[float, ...], ...]:
        """Per entity, per token: its clip length (source frames) if the vocab's kind is "event", else 0 (a loop,
        token 0): how long an action that ends on its own lasts."""
        return tuple(
            tuple(float(n) if k == "event" else 0.0 for k, n in zip(kinds, lengths))
            for kinds, lengths in zip(self.token_field(vocab, "kind"), self.clip_lengths)
        )

    def class_indices(self, vocab: dict) -> tuple[tuple[int, ...], ...]:
        """Per entity, per token: 1 + the index of its vocab class in ``MOTION_CLASSES`` (0 for token 0 and for a
        class the list lacks)."""
        return tuple(
            tuple(MOTION_CLASSES.index(c) + 1 if c in MOTION_CLASSES else 0 for c in classes)
            for classes in self.token_field(vocab, "class")
        )

    @classmethod
    def from_corpus(cls, corpus: Corpus | Path | str) -> ActionTokens:
        """Entity token tables of a corpus (its vocab.json and layout)."""
        c = corpus if isinstance(corpus, Corpus) else Corpus(Path(corpus))
        fps = c.info.fps
        one_rate = not isinstance(fps, list) or len(set(fps)) == 1  # recordings at several rates: δ unknown, 0
        return cls.from_vocab(c.vocab, c.layout, c.fps if one_rate else 0.0)

    def encode(self, layout: Layout, table: pa.Table, where: str = "") -> tuple[np.ndarray, np.ndarray]:
        """State rows → tokens (n, N) int64 and progress (n, N) float32 in [0, 1]; an id the vocab lacks
        is a ValueError naming the segment, the row within it and the source frame.

        Progress = (motion_frame + δ) / clip length, δ the row's time past its source frame in source frames,
        t · source_fps − frame (0 on a source row; 0 or ½ on a 20 fps row of a 30 fps corpus, which carries the
        source frame at or before its time), so along a resampled run progress grows at the rate a rollout advances
        it. Without ``source_fps`` (or a ``t`` column) δ = 0."""
        n = table.num_rows
        late = np.zeros(n, np.float64)
        if self.source_fps > 0 and n and "t" in table.column_names:
            t = table["t"].to_numpy().astype(np.float64)
            late = np.clip(t * self.source_fps - table["frame"].to_numpy().astype(np.float64), 0.0, None)
        tokens = np.zeros((n, len(self.entities)), np.int64)
        progress = np.zeros((n, len(self.entities)), np.float32)
        for i, e in enumerate(layout.articulated):
            types = table[f"{e.name}.type_id"].to_numpy().astype(np.int64)
            acts = table[f"{e.name}.action"].to_numpy().astype(np.int64)
            mf = table[f"{e.name}.motion_frame"].to_numpy().astype(np.float64)
            nz = np.flatnonzero(acts != 0)
            if len(nz):
                keys, inverse = np.unique(types[nz] * (1 << 32) + acts[nz], return_inverse=True)
                lut = np.empty(len(keys), np.int64)
                for k, key in enumerate(keys):
                    type_id, cid = int(key >> 32), int(key & 0xFFFFFFFF)
                    tok = self.lookup[i].get((type_id, cid))
                    if tok is None:
                        self._unknown(table, where, e, type_id, cid, int(nz[np.flatnonzero(inverse == k)[0]]))
                    lut[k] = tok
                tokens[nz, i] = lut[inverse.reshape(-1)]
            clip = self.clip_lengths[i][tokens[:, i]]
            p = np.clip(np.where(mf >= 0, mf + late, 0.0) / clip, 0.0, 1.0)
            progress[:, i] = np.where(tokens[:, i] == 0, 0.0, p)
        return tokens, progress

    def _unknown(self, table: pa.Table, where: str, e: Entity, type_id: int, cid: int, row: int) -> NoReturn:
        segs = table["segment"].to_numpy(zero_copy_only=False)
        seg = segs[row]
        first = int(np.flatnonzero(segs == seg)[0])
        frame = int(table["frame"][row].as_py())
        key = entity_type_key(e, type_id)
        typed = key in self.type_keys[self.entities.index(e.name)]
        missing = f"no action {cid} of type {key}" if typed else f"no entity type {key}"
        raise ValueError(
            f"{where + ': ' if where else ''}segment {seg}, row {row - first} (source frame {frame}): {e.name} ({key}) "
            f"has composite action id {cid}, but vocab.json (hash {self.vocab_hash}) holds {missing}; "
            f"re-run finalize if recordings were added"
        )

    def type_token(self, entity: int, token: int) -> tuple[str, int]:
        """The (vocab.json type key, token within that type's vocab) of an entity token; ("", 0) for token 0."""
        return self.type_keys[entity][token], int(self.vocab_tokens[entity][token])
