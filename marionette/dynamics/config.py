"""What fixes a dynamics model and a training run of it: the transformer sizes (``TransformerSpec``, the
``PRESETS``), the model's config (``DynamicsConfig``, from a scene layout) and the training run's knobs
(``TrainConfig``). Importable without torch: ``marionette train dynamics --help`` reads it."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

from marionette.corpus import MODEL_FPS
from marionette.dynamics.state import body_index, root_index, weapon_range
from marionette.io import check_json_fields
from marionette.knobs import check_knobs, knob
from marionette.model_size import (
    MAX_HEADS,
    MAX_LAYERS,
    MAX_VOCAB,
    MAX_WIDTH,
    MAX_WINDOW,
    check_int,
    check_memory,
    transformer_parameters,
)
from marionette.schema import Layout, SchemaError

PATCH_SIZE = 11  # egocentric height patch, cells per side
N_CLEARANCES = 11  # signed clearances of key joints
TERRAIN_FEATURES = PATCH_SIZE * PATCH_SIZE + N_CLEARANCES
ROOT_PER_ENTITY = 9  # root stream per articulated entity: E.root (3) then E.rot6d (6)
N_TOKEN_CLASSES = 4  # motion classes a token may name (corpus.vocab.MOTION_CLASSES); 0 = none


@dataclass(frozen=True)
class TransformerSpec:
    """Size of one causal transformer and of its per-frame encoders."""

    layers: int
    width: int
    heads: int
    action_embed: int  # learned action embedding per entity
    terrain_out: int  # terrain MLP output per terrain-on entity
    terrain_hidden: int = 128
    mlp_ratio: int = 4

    def __post_init__(self) -> None:
        for name, high in (
            ("layers", MAX_LAYERS),
            ("width", MAX_WIDTH),
            ("heads", MAX_HEADS),
            ("action_embed", MAX_WIDTH),
            ("terrain_out", MAX_WIDTH),
            ("terrain_hidden", MAX_WIDTH),
            ("mlp_ratio", 16),
        ):
            check_int(getattr(self, name), name, 1, high, "transformer spec")

    @property
    def head_dim(self) -> int:
        return self.width // self.heads

    @property
    def parameters(self) -> int:
        """The blocks' parameters (the encoders' and heads' are small beside them)."""
        return transformer_parameters(self.layers, self.width, self.mlp_ratio)


PRESETS: dict[str, dict[str, Any]] = {
    "paper": {
        "action_gpt": TransformerSpec(layers=4, width=256, heads=8, action_embed=32, terrain_out=32),
        "pose_gpt": TransformerSpec(layers=8, width=512, heads=8, action_embed=64, terrain_out=64),
        "window": 512,
    },
    "tiny": {
        "action_gpt": TransformerSpec(layers=2, width=64, heads=4, action_embed=16, terrain_out=32, terrain_hidden=64),
        "pose_gpt": TransformerSpec(layers=2, width=96, heads=4, action_embed=16, terrain_out=64, terrain_hidden=64),
        "window": 64,
    },
}


@dataclass(frozen=True)
class DynamicsConfig:
    """Everything that fixes the dynamics model's parameter set; saved as JSON beside its checkpoints.

    The heads. ActionGPT's root head predicts the next displacements outright and, with ``rotation_anchor``, each
    next rotation as rot6d[t] + Δ (the rollout re-orthonormalises it). With ``displacement_gate``, each next
    displacement is g · carried + (1 − g) · head, g = sigmoid(gate head) in (0, 1) per dimension, carried =
    ``frames.skip`` when given, else root[t]: a rollout passes its own proposal of root[t], before the rules
    corrected it (a carried correction of the separation cap, which moves both bodies by half the excess, would
    become a common motion of both; the transformer still reads the corrected root), and g is 0 where an action
    starts (``ActionGPT.action_starts``): a new action's first displacement is the head's. The head learns on its own
    (its proposal, ``ActionOutputs.proposal``, has its own loss) and the blend holds it fixed, so the blend's loss
    trains the gate; over four seeds the gate beats constant velocity one step ahead on every one (docs/tradeoffs.md,
    "Seed to seed"), so training turns it on by default (``TrainConfig``). PoseGPT's body head, with
    ``body_anchor``, predicts body[t+1] = g ⊙ body[t] + Δ with g one learned gain per body dimension (starting at
    1); without an anchor, that part is predicted outright. ``residual`` (for comparison; it excludes the anchors
    and the gate) makes both heads add Δ to the current frame with gain 1.

    Every output head starts at zero, so an untrained model predicts its anchors: copy-last body and rotations,
    sigmoid(``GATE_INIT``) = 0.88 of the current displacement (the mean without the gate), and (with ActionGPT's
    copy gain) the current action; with ``adaptive_copy`` the copy gain gets a per-frame term from a stay head
    (starting at 0), so the model can let go of the current action where it expects a change without outbidding a
    gain of ~7 with one token's logit. Residual heads drift in long rollouts, and so does a learned gain on the
    displacement (it amplifies the head's bias by 1/(1 − g): kilometres over 10,000 frames, docs/tradeoffs.md);
    the gate's g stays below 1 and its carried displacement is the model's own.
    """

    scene: str
    layout_hash: str
    entities: tuple[str, ...]  # articulated entities, layout order
    root_dim: int
    body_dim: int
    weapon: tuple[int, int]  # [start, stop) of the attachments' points within the body state
    vocab_sizes: tuple[int, ...]  # per articulated entity; token 0 = no valid action
    action_gpt: TransformerSpec
    pose_gpt: TransformerSpec
    window: int  # attention window, frames
    terrain: tuple[bool, ...]  # per articulated entity: read its terrain features
    terrain_features: int = TERRAIN_FEATURES
    relative_position: bool = False  # read the other entity's root in my root frame (3 per entity)
    residual: bool = False  # heads predict a change added to the current frame's value
    body_anchor: bool = False  # PoseGPT predicts gain ⊙ body[t] + Δ, a learned gain per dimension (init 1)
    rotation_anchor: bool = False  # ActionGPT predicts every E.rot6d as rot6d[t] + Δ (displacements stay absolute)
    # ActionGPT predicts every E.root as g · root[t] + (1 − g) · head, g = sigmoid(gate head) in (0, 1) per dimension
    displacement_gate: bool = False
    # ActionGPT's copy gain on the current token gets a learned, frame-dependent term (``stay_head``, from 0)
    adaptive_copy: bool = False
    # PoseGPT reads each entity's progress in its action at the frame being animated (beyond the paper, whose PoseGPT
    # reads the tokens alone): where in its clip a forced or recorded token is
    pose_progress: bool = False
    dropout: float = 0.0
    # per entity, per token: its motion class (1 + index in corpus.vocab.MOTION_CLASSES, 0 none); when given, a
    # learned class embedding is added to every token's, so a rarely played token starts from its class's motion
    token_classes: tuple[tuple[int, ...], ...] = ()
    # per entity, per token: the clip length in source frames of a token that ends on its own (an event; the vocab's
    # clip_length), 0 for one that does not (a loop, token 0); when given, ActionGPT reads each entity's time left
    # in its event (``time_left``), which is when the next action starts
    clip_frames: tuple[tuple[float, ...], ...] = ()
    source_fps: float = 30.0  # the rate clip_frames count at (the corpus's)
    # a played-out event ends: where an entity's current token has clip_frames L > 0 and at most source_fps / model_fps
    # source frames left, (1 − progress) · L ≤ that, the next token is another (its logit is dropped); per entity, per
    # token, the lengths this rule uses: clip_frames, 0 where the train split saw the token run on (``ended_events``)
    events_end: tuple[tuple[float, ...], ...] = ()
    model_fps: float = MODEL_FPS  # the rate the model steps at (the corpus's dynamics view)

    def __post_init__(self) -> None:
        n = len(self.entities)
        for name in ("clip_frames", "events_end"):  # per entity, per token: a length in source frames, or 0
            table = getattr(self, name)
            if table and (
                len(table) != n
                or any(len(t) != v for t, v in zip(table, self.vocab_sizes))
                or any(not (x >= 1 or x == 0) for t in table for x in t)
            ):
                raise ValueError(
                    f"dynamics config: {name} must give each of the {n} entities one length (≥ 1, or 0) per token "
                    f"(vocab sizes {self.vocab_sizes})"
                )
        if not self.source_fps > 0 or not self.model_fps > 0:
            raise ValueError(f"dynamics config: source_fps {self.source_fps} and model_fps {self.model_fps} must be > 0")
        if self.token_classes and (
            len(self.token_classes) != n
            or any(len(t) != v for t, v in zip(self.token_classes, self.vocab_sizes))
            or any(not 0 <= x <= N_TOKEN_CLASSES for t in self.token_classes for x in t)
        ):
            raise ValueError(
                f"dynamics config: token_classes must give each of the {n} entities one class in 0..{N_TOKEN_CLASSES} "
                f"per token (vocab sizes {self.vocab_sizes})"
            )
        if len(self.vocab_sizes) != n or len(self.terrain) != n:
            raise ValueError(
                f"dynamics config: {n} articulated entities {self.entities} but {len(self.vocab_sizes)} vocab sizes "
                f"and {len(self.terrain)} terrain switches"
            )
        if any(v < 1 for v in self.vocab_sizes):
            raise ValueError(f"dynamics config: vocab sizes {self.vocab_sizes} must be ≥ 1 (token 0 = no valid action)")
        check_int(self.window, "window", 1, MAX_WINDOW, "dynamics config")
        for v in self.vocab_sizes:
            check_int(v, "vocab size", 1, MAX_VOCAB, "dynamics config")
        for name in ("root_dim", "body_dim", "terrain_features"):
            check_int(getattr(self, name), name, 0, 1 << 20, "dynamics config")
        if self.residual and (self.body_anchor or self.rotation_anchor or self.displacement_gate):
            raise ValueError(
                "dynamics config: residual (both heads, gain 1) excludes body_anchor, rotation_anchor and displacement_gate"
            )
        for name, spec in (("action_gpt", self.action_gpt), ("pose_gpt", self.pose_gpt)):
            if not isinstance(spec, TransformerSpec):
                raise ValueError(f"dynamics config: {name} is not a transformer spec")
            if spec.width % spec.heads or spec.head_dim % 2:
                raise ValueError(
                    f"dynamics config: {name} width {spec.width} must split into {spec.heads} heads of even size (RoPE)"
                )
        embeddings = sum(self.vocab_sizes) * (self.action_gpt.width + self.pose_gpt.width)
        check_memory(self.action_gpt.parameters + self.pose_gpt.parameters + embeddings, "dynamics config")

    @property
    def n_entities(self) -> int:
        return len(self.entities)

    @property
    def weapon_dim(self) -> int:
        return self.weapon[1] - self.weapon[0]

    @classmethod
    def from_layout(cls, layout: Layout, vocab_sizes: tuple[int, ...], **options: Any) -> DynamicsConfig:
        """A config whose dimensions come from ``layout``; ``options`` are the remaining fields.

        ``terrain`` defaults to on for monsters (entities recorded as WildWorld kind ``m``) only."""
        root_dim, body_dim = len(root_index(layout)), len(body_index(layout))
        if root_dim + body_dim != layout.dim:
            raise SchemaError(f"layout {layout.scene!r}: root stream ({root_dim}) + body ({body_dim}) ≠ state dim {layout.dim}")
        options.setdefault("terrain", tuple(e.source_kind == "m" for e in layout.articulated))
        return cls(
            scene=layout.scene,
            layout_hash=layout.hash,
            entities=tuple(e.name for e in layout.articulated),
            root_dim=root_dim,
            body_dim=body_dim,
            weapon=weapon_range(layout),
            vocab_sizes=tuple(int(v) for v in vocab_sizes),
            **options,
        )

    @classmethod
    def preset(cls, name: str, layout: Layout, vocab_sizes: tuple[int, ...], **overrides: Any) -> DynamicsConfig:
        """The ``"paper"`` or ``"tiny"`` sizes for ``layout``; ``overrides`` replace any field (e.g. ``window=16``)."""
        if name not in PRESETS:
            raise ValueError(f"unknown dynamics preset {name!r}; known: {sorted(PRESETS)}")
        return cls.from_layout(layout, vocab_sizes, **{**PRESETS[name], **overrides})

    def check_layout(self, layout: Layout) -> None:
        """Fail, naming both, unless ``layout`` is the one this config was made for."""
        if layout.hash != self.layout_hash:
            raise SchemaError(
                f"dynamics config was made for layout {self.scene!r} (hash {self.layout_hash}), "
                f"not {layout.scene!r} (hash {layout.hash})"
            )

    def to_json(self) -> dict:
        """The config as a plain JSON-ready dict."""
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, TransformerSpec):
                v = {g.name: getattr(v, g.name) for g in fields(v)}
            elif isinstance(v, tuple):
                v = list(v)
            out[f.name] = v
        return out

    @classmethod
    def from_json(cls, d: dict) -> DynamicsConfig:
        """Rebuild a config from ``to_json()``."""
        check_json_fields(cls, d, "dynamics config")
        kw: dict[str, Any] = {}
        for k, v in d.items():
            if k in ("action_gpt", "pose_gpt"):
                if not isinstance(v, dict):
                    raise ValueError(f"dynamics config JSON: {k} is not an object")
                check_json_fields(TransformerSpec, v, f"dynamics config {k}")
                v = TransformerSpec(**v)
            elif k == "token_classes" and isinstance(v, list):
                v = tuple(tuple(int(x) for x in t) for t in v)
            elif k in ("clip_frames", "events_end") and isinstance(v, list):
                v = tuple(tuple(float(x) for x in t) for t in v)
            elif isinstance(v, list):
                v = tuple(bool(x) if k == "terrain" else x for x in v)
            kw[k] = v
        return cls(**kw)


@dataclass(frozen=True)
class TrainConfig:
    """Every knob of a training run; saved as JSON in each checkpoint's meta."""

    preset: str = knob("tiny", "model size (dynamics.config.PRESETS)", choices=sorted(PRESETS))
    scene: str | None = knob(
        None, "the scene to train on, in a corpus of several (a species slice); default: the corpus's only scene"
    )
    steps: int = knob(1000, "optimizer steps in all (the length of the LR schedule)", min=1)
    batch_size: int = knob(16, "windows per step and process", min=1)
    loader_workers: int = knob(
        0, "DataLoader worker processes stacking each rank's batches; 0: in the training process (same batches either way)", min=0
    )
    window: int | None = knob(None, "model steps per window; default: the preset's, capped to the train segments", min=1)
    lr: float = knob(3e-4, "peak learning rate", above=0.0)
    betas: tuple[float, float] = knob((0.9, 0.95), "AdamW betas", min=0.0, below=1.0)
    weight_decay: float = knob(0.1, "AdamW weight decay (matrices and embeddings only)", min=0.0)
    warmup: int = knob(100, "linear warm-up steps", min=0)
    min_lr_ratio: float = knob(0.1, "the cosine decays to this fraction of lr", min=0.0, max=1.0)
    grad_clip: float = knob(1.0, "gradient-norm clipping", above=0.0)
    seed: int = knob(0, "seed of the initial weights, the windows drawn and the input noise", min=0)
    terrain: bool = knob(True, "load terrain features: monsters read them (DynamicsConfig.from_layout), the hinge uses them")
    # the relative position is what the fighters' behaviour turns on (the hunter keeps its distance and circles, the
    # drake turns to face it): on, free rollouts keep the pair together and the probe's count steadies over seeds
    relative: bool = knob(True, "the relative-position feature (DESIGN: beyond the paper)")
    pose_progress: bool = knob(True, "PoseGPT reads the progress of each token it animates (beyond the paper)")
    dropout: float = knob(0.0, "dropout in both transformers", min=0.0, below=1.0)
    # Long rollouts (docs/tradeoffs.md): residual heads integrate their errors and leave the data; a learned gain on
    # the body anchor (it falls below 1 on noised inputs) keeps bones steady over 10,000 frames; on the displacement
    # it ran off by kilometres, so displacements are absolute unless ``displacement_gate`` blends in the current one (in a
    # rollout: the model's own proposal, not the rules' correction of it). Untrained, the anchors are the baselines.
    # The gate and PoseGPT's progress are the defaults: over four seeds they beat constant velocity on every seed and
    # raised the probe and forcing means (docs/tradeoffs.md, "Seed to seed"). events_end is on: an event that has played
    # out gives way (by the vocab's definition an event never wraps), so at an event's end the model names what follows
    # (the game's recovery) where copy-last cannot; time_left and adaptive_copy stay off (they cost the probe).
    residual: bool = knob(False, "both heads add a change to the current frame, gain 1 (DynamicsConfig.residual)")
    token_classes: bool = knob(True, "add a learned embedding of each token's motion class (DynamicsConfig.token_classes)")
    time_left: bool = knob(False, "ActionGPT reads each event's time left (DynamicsConfig.clip_frames)")
    events_end: bool = knob(True, "a played-out event is followed by another token (DynamicsConfig.events_end)")
    body_anchor: bool = knob(True, "PoseGPT predicts gain ⊙ current body + a change, a gain per dimension; off with residual")
    rotation_anchor: bool = knob(True, "ActionGPT predicts each root rotation as the current one + a change; off with residual")
    adaptive_copy: bool = knob(False, "ActionGPT's copy gain on the current token gets a learned per-frame term")
    displacement_gate: bool = knob(
        True, "ActionGPT predicts each displacement as g · the current one + (1 − g) · a head, g a learned gate in (0, 1)"
    )
    input_noise: float = knob(
        0.1, "std (normalised units) of Gaussian noise on the models' body inputs and PoseGPT's root inputs", min=0.0
    )
    root_noise: float | None = knob(
        None,
        "std of the Gaussian noise on ActionGPT's root inputs; None: 0 with the gate (it carries them), else input_noise",
        min=0.0,
    )
    w_action: float = knob(1.0, "weight of the next-action cross-entropy", min=0.0)
    label_smoothing: float = knob(0.1, "label smoothing of the next-action cross-entropy", min=0.0, below=1.0)
    w_root: float = knob(1.0, "weight of the next-root MSE", min=0.0)
    w_body: float = knob(1.0, "weight of the next-body MSE", min=0.0)
    w_drift: float = knob(0.1, "weight of the vertical-drift term", min=0.0)
    w_hinge: float = knob(0.1, "weight of the penetration hinge", min=0.0)
    hinge_margin: float = knob(0.15, "metres, DESIGN's ReLU(H_j + margin − y_j)²")
    eval_every: int = knob(0, "evaluate on the held-out windows every N steps; 0: only at the end", min=0)
    eval_batch_size: int = knob(64, "held-out windows per evaluation batch", min=1)
    checkpoint_every: int = knob(0, "checkpoint every N steps; 0: only at the end", min=0)
    bf16: bool | None = knob(None, "bf16 autocast; default: where the hardware has it (CUDA with bf16)")
    fps: float = knob(MODEL_FPS, "frame rate the model runs at (the dynamics view's, resampled from the corpus)", above=0.0)

    def __post_init__(self) -> None:
        check_knobs(self)

    def to_json(self) -> dict:
        d = asdict(self)
        d["betas"] = list(self.betas)
        return d

    @classmethod
    def from_json(cls, d: dict) -> TrainConfig:
        check_json_fields(cls, d, "train config")
        return cls(**{**d, **({"betas": tuple(d["betas"])} if "betas" in d else {})})
