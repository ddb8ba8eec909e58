"""What fixes an observation model and a training run of it: the network's config (``ObservationConfig``, its
``OBS_PRESETS``), a training run's knobs (``ObservationTrainConfig``) and a Wan fine-tuning run's
(``WanTrainConfig``). Importable without torch: ``marionette train observation --help`` reads it."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from marionette.chunks import is_clip_length
from marionette.io import check_json_fields
from marionette.knobs import check_knobs, knob
from marionette.model_size import (
    MAX_HEADS,
    MAX_LAYERS,
    MAX_PIXELS,
    MAX_VOCAB,
    MAX_WIDTH,
    check_int,
    check_memory,
    transformer_parameters,
)

REFERENCE_SWAP = 0.2  # the default under pose control (docs/tradeoffs.md, "Observation: reference swap ...")

RGB, POSE = 3, 3
CONTROLS = ("pose", "actions")
FORMAT = 2


@dataclass(frozen=True)
class ObservationConfig:
    """Everything that fixes the network's parameter set; saved as JSON beside its checkpoints."""

    frames: int = 9  # clip length, 4k + 1
    height: int = 36
    width_px: int = 64
    patch: int = 4
    width: int = 128
    layers: int = 4
    heads: int = 4
    mlp_ratio: int = 4
    control: str = "pose"  # "pose": pose-control frames; "actions": the pixel-AR baseline's action schedule
    vocab_sizes: tuple[int, ...] = ()  # per articulated entity, for control "actions"
    # what the inputs mean. 2: the first frame on frame 0's tokens only. A checkpoint without it gave the first
    # frame to every frame's tokens: its parameters have the same shapes but would paint wrong video here.
    format: int = FORMAT
    # persistent entity references (observation.references): the render-id band [first, last] of each entity slot,
    # and a reference's side in pixels; () and 0: none
    reference_bands: tuple[tuple[int, int], ...] = ()
    reference_size: int = 0
    reference_paint: bool = False  # the references also laid over their bodies in every frame (references.paint)
    # conditioning augmentation of the given frame against a relay's drift: trained on first frames noised by
    # N(0, σ²) with σ uniform in [0, handoff_noise] (RGB units), σ told to the network; a relay gives each hand-off
    # frame noised at handoff_level (0: none, the network has no input for it)
    handoff_noise: float = 0.0

    def __post_init__(self) -> None:
        for name, low, high in (
            ("frames", 5, 1025),
            ("height", 1, MAX_PIXELS),
            ("width_px", 1, MAX_PIXELS),
            ("patch", 1, 64),
            ("width", 1, MAX_WIDTH),
            ("layers", 1, MAX_LAYERS),
            ("heads", 1, MAX_HEADS),
            ("mlp_ratio", 1, 16),
            ("reference_size", 0, MAX_PIXELS),
        ):
            check_int(getattr(self, name), name, low, high, "observation config")
        for v in self.vocab_sizes:
            check_int(v, "vocab size", 1, MAX_VOCAB, "observation config")
        if self.format != FORMAT:
            raise ValueError(f"observation config: format {self.format}; this version reads format {FORMAT} (retrain the model)")
        if self.control not in CONTROLS:
            raise ValueError(f"observation config: control {self.control!r} is not one of {CONTROLS}")
        if self.control == "actions" and not self.vocab_sizes:
            raise ValueError("observation config: an action-conditioned model needs vocab_sizes")
        if not is_clip_length(self.frames):
            raise ValueError(f"observation config: frames {self.frames} must be 4k + 1 with k ≥ 1")
        if self.height % self.patch or self.width_px % self.patch:
            raise ValueError(
                f"observation config: {self.height}×{self.width_px} is not a whole number of {self.patch}-pixel patches"
            )
        if self.width % self.heads:
            raise ValueError(f"observation config: width {self.width} does not split into {self.heads} heads")
        if (
            isinstance(self.handoff_noise, bool)
            or not isinstance(self.handoff_noise, int | float)
            or not 0 <= self.handoff_noise <= 2
        ):
            raise ValueError(f"observation config: handoff_noise {self.handoff_noise} is not within [0, 2]")
        if not isinstance(self.reference_paint, bool):
            raise ValueError(f"observation config: reference_paint {self.reference_paint!r} is not true or false")
        if self.reference_bands:
            if self.reference_size < self.patch or self.reference_size % self.patch:
                raise ValueError(
                    f"observation config: reference_size {self.reference_size} is not a whole number of {self.patch}-pixel patches"
                )
            for a, b in self.reference_bands:
                if not 1 <= a <= b <= 254:
                    raise ValueError(f"observation config: reference band [{a}, {b}] is not within the render ids 1–254")
            if self.control != "pose":
                raise ValueError("observation config: entity references need pose control (their masks come from it)")
        elif self.reference_size or self.reference_paint:
            raise ValueError("observation config: reference_size or reference_paint without reference_bands")
        check_memory(transformer_parameters(self.layers, self.width, self.mlp_ratio), "observation config")

    @property
    def size(self) -> tuple[int, int]:
        return self.height, self.width_px

    @property
    def tokens(self) -> int:
        return self.frames * (self.height // self.patch) * (self.width_px // self.patch)

    @property
    def in_channels(self) -> int:
        """Per pixel: noisy RGB, the pose frame (pose control only), the given frame (the first frame on frame 0,
        zeros after) and its mask, and (``reference_paint``) the references laid over their bodies and their mask."""
        return RGB + (POSE if self.control == "pose" else 0) + RGB + 1 + (RGB + 1 if self.reference_paint else 0)

    @property
    def handoff_level(self) -> float:
        """The noise σ a relay adds to each hand-off frame (the middle of the trained range; 0 without)."""
        return self.handoff_noise / 2

    @property
    def references(self) -> int:
        """Entity reference slots (0: a model without references)."""
        return len(self.reference_bands)

    def to_json(self) -> dict:
        d = asdict(self)
        d["vocab_sizes"] = list(self.vocab_sizes)
        d["reference_bands"] = [list(b) for b in self.reference_bands]
        return d

    @classmethod
    def from_json(cls, d: dict) -> ObservationConfig:
        check_json_fields(cls, d, "observation config")
        if "format" not in d:
            raise ValueError(
                "observation config JSON has no format: a model from before format 2 (first frame on every frame's "
                "tokens), which this version would run wrongly; retrain it"
            )
        bands = d.get("reference_bands", ())
        if not isinstance(bands, list | tuple) or not all(
            isinstance(b, list | tuple) and len(b) == 2 and all(isinstance(v, int) and not isinstance(v, bool) for v in b)
            for b in bands
        ):
            raise ValueError(f"observation config JSON: reference_bands {bands!r} is not a list of [first, last] ids")
        return cls(**{**d, "vocab_sizes": tuple(d.get("vocab_sizes", ())), "reference_bands": tuple(tuple(b) for b in bands)})


OBS_PRESETS = {
    "tiny": ObservationConfig(frames=9, height=36, width_px=64, patch=4, width=96, layers=3, heads=4),
    "small": ObservationConfig(frames=17, height=88, width_px=160, patch=8, width=256, layers=8, heads=8),
}


@dataclass(frozen=True)
class ObservationTrainConfig:
    """Every knob of an observation training run; saved in each checkpoint's meta."""

    preset: str = knob("tiny", "network size (observation.config.OBS_PRESETS)", choices=sorted(OBS_PRESETS))
    steps: int = knob(1000, "optimizer steps in all (the length of the LR schedule)", min=1)
    batch_size: int = knob(4, "clips per step and process", min=1)
    frames: int | None = knob(None, "clip length in frames, 4k + 1; default: the preset's", min=5)
    reduce: int = knob(4, "the corpus chunk's height and width divided by the model's", min=1)
    patch: int | None = knob(None, "patch side in pixels; default: the preset's", min=1)
    lr: float = knob(3e-4, "peak learning rate", above=0.0)
    warmup: int = knob(50, "linear warm-up steps", min=0)
    seed: int = knob(0, "seed of the initial weights, the clips drawn and the noise", min=0)
    checkpoint_every: int = knob(0, "checkpoint every N steps; 0: only at the end", min=0)
    cache_mb: int = knob(
        2048, "decoded chunks kept in memory per split (MiB, least recently used evicted); results do not depend on it", min=0
    )
    control: str = knob(
        "pose", "pose: pose-control video; actions: the pixel-AR baseline (first frame + action schedule)", choices=CONTROLS
    )
    # None: 0.2 under pose control, 0 for the baseline (which can learn where bodies are only from its first frame)
    reference_swap: float | None = knob(
        None,
        "probability that a training clip's first frame comes from another chunk "
        "(teaches pose-following); default: 0.2 under pose control, 0 for the baseline",
        min=0.0,
        below=1.0,
    )

    references: bool = knob(
        False,
        "give every clip a crop of each entity from its chunk's frames up to the clip's start, taken as a relay "
        "takes it (persistent references against appearance drift over a relay; observation.references)",
    )
    reference_paint: bool = knob(
        True,
        "with --references: also lay each entity's crop over its pixels in every frame's control (four more input "
        "channels a pixel); off: the references are only read as tokens (docs/tradeoffs.md, 'Persistent entity references')",
    )
    first_frame_drift: float = knob(
        0.0,
        "each entity's pixels in a clip's given first frame shifted by a random colour (per channel, this standard "
        "deviation in [-1, 1] units), as a relayed frame's drifted look: teaches the model to take a body's look "
        "from its references",
        min=0.0,
        max=2.0,
    )
    handoff_noise: float = knob(
        0.0,
        "each clip's given first frame noised by N(0, σ²), σ uniform in [0, this] (RGB in [-1, 1]) and told to the "
        "network; a relay gives its hand-off frames noised at half this (conditioning augmentation against drift)",
        min=0.0,
        max=2.0,
    )
    jitter_root_m: float = knob(
        0.0, "training targets rendered from state whose roots are shifted this far (m; bridge.jitter)", min=0.0
    )
    jitter_joint_deg: float = knob(
        0.0, "training targets rendered from state whose bones are turned by up to this (°)", min=0.0, max=45.0
    )
    jitter_time_s: float = knob(0.0, "training targets rendered from state whose time is warped by up to this (s)", min=0.0)

    def __post_init__(self) -> None:
        check_knobs(self)
        if self.frames is not None and not is_clip_length(self.frames):
            raise ValueError(f"ObservationTrainConfig.frames: clips are 4k + 1 frames, not {self.frames}")
        if self.reference_swap and self.control != "pose":
            raise ValueError("reference_swap needs pose control: the baseline learns where bodies are from its first frame")
        if self.first_frame_drift and self.control != "pose":
            raise ValueError("first_frame_drift needs pose control: the entities' pixels are found by the pose frame's id mask")
        if self.references and self.control != "pose":
            raise ValueError("references need pose control: an entity's crop is found by the pose frame's id mask")

    @property
    def swap(self) -> float:
        """The reference-swap probability in effect."""
        if self.reference_swap is not None:
            return self.reference_swap
        return REFERENCE_SWAP if self.control == "pose" else 0.0

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> ObservationTrainConfig:
        check_json_fields(cls, d, "observation train config")
        return cls(**d)


@dataclass(frozen=True)
class WanTrainConfig:
    """Every knob of a Wan fine-tuning run; saved in each checkpoint's meta."""

    backbone: str = knob("", "the Wan2.2-Fun-Control checkpoint directory to start from (release or diffusers layout)")
    steps: int = knob(1000, "optimizer steps in all (the length of the LR schedule)", min=1)
    batch_size: int = knob(1, "windows per step and process", min=1)
    frames: int = knob(81, "window length in frames, 4k + 1", min=5)
    reduce: int = knob(1, "the corpus chunk's height and width divided by the backbone's input", min=1)
    lr: float = knob(1e-4, "peak learning rate", above=0.0)
    warmup: int = knob(50, "linear warm-up steps", min=0)
    seed: int = knob(0, "seed of the windows drawn, the noise and the LoRA initialisation", min=0)
    lora_rank: int = knob(0, "LoRA rank on the attention and feed-forward layers; 0: every weight trains", min=0)
    lora_alpha: float | None = knob(None, "LoRA scale numerator (alpha / rank scales the update); default: the rank", above=0.0)
    shift: float = knob(5.0, "Wan's timestep shift of the training σ", above=0.0)
    max_chunks: int = knob(0, "train on the first N chunks of the train split (and of the held-out split); 0: all", min=0)
    bf16: bool = knob(False, "bf16 autocast of the transformer's forward pass")
    gradient_checkpointing: bool = knob(False, "recompute each block's activations in the backward pass")
    checkpoint_every: int = knob(0, "checkpoint every N steps; 0: only at the end", min=0)
    jitter_root_m: float = knob(
        0.0, "training targets rendered from state whose roots are shifted this far (m; bridge.jitter)", min=0.0
    )
    jitter_joint_deg: float = knob(
        0.0, "training targets rendered from state whose bones are turned by up to this (°)", min=0.0, max=45.0
    )
    jitter_time_s: float = knob(0.0, "training targets rendered from state whose time is warped by up to this (s)", min=0.0)
    references: bool = knob(
        False, "give every window a sheet of each entity's first look in its chunk up to the window's start (ref_conv)"
    )
    fsdp: bool = knob(
        False,
        "with several processes, shard the weights, gradients and optimizer state over them (FSDP2, each transformer "
        "block a unit) instead of copying the model to each (DDP); checkpoints stay whole; one process: no effect",
    )
    device: str = knob(
        "cpu", "where the transformer trains: cpu, or cuda (each process its LOCAL_RANK's GPU)", choices=("cpu", "cuda")
    )

    def __post_init__(self) -> None:
        check_knobs(self)
        if not is_clip_length(self.frames):
            raise ValueError(f"WanTrainConfig.frames: windows are 4k + 1 frames, not {self.frames}")
        if not self.backbone:
            raise ValueError("WanTrainConfig.backbone: the Wan checkpoint directory to fine-tune is required")
        if self.device == "cuda":
            import torch  # only a run asking for a GPU needs torch, to look for one: the config is read without it

            if not torch.cuda.is_available():
                raise ValueError(
                    "WanTrainConfig.device: cuda, and this torch sees no CUDA GPU (torch.cuda.is_available() is False)"
                )

    @property
    def alpha(self) -> float:
        return float(self.lora_alpha if self.lora_alpha is not None else self.lora_rank)

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> WanTrainConfig:
        check_json_fields(cls, d, "Wan train config")
        return cls(**d)
