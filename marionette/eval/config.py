"""What fixes an evaluation: its counts and lengths (``EvalProtocol``), checked when made, the named ones
(``PROTOCOLS``: "paper", the paper's, and "quick", the demo's) and ``parse_protocol``; ``reduced`` lists what is
smaller than the paper's. Table 3's state columns may run on more and longer rollouts (``state_rollouts`` ×
``state_seconds``) than Tables 1 and 3 paint: the painted rollouts are the first ``rollouts`` of them, cut to
``rollout_seconds``. The paper's are the same rollouts; the quick protocol paints 2 × 3 s and measures the rules on
8 × 9 s. Every count is a knob (``knobs.knob``): ``marionette eval`` generates its flags from the fields in
``OVERRIDES``, each overriding the chosen protocol's. Importable without torch: ``marionette eval --help`` reads it."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

from marionette.knobs import knob

# the fields ``marionette eval`` takes as flags, each overriding the chosen protocol's
OVERRIDES = ("probe_windows", "seed_frames", "horizon", "rollouts", "rollout_seconds", "state_rollouts", "state_seconds")
OVERRIDES += ("fvd_steps",)


@dataclass(frozen=True)
class EvalProtocol:
    """The counts and lengths of one evaluation (DESIGN "Evaluation definitions"); ``PROTOCOLS`` names the paper's and
    the demo's. Frames are dynamics frames (the model's rate) unless named video frames."""

    name: str
    probe_windows: int = knob(
        48, "probe windows (Table 2's held-out windows, and the Free state layer's)", min=1, flag="--segments"
    )
    seed_frames: int = knob(64, "recorded frames seeding every rollout", min=1)
    horizon: int = knob(120, "predicted frames of each probe window", min=1)
    rollouts: int = knob(32, "long rollouts of Tables 1 and 3 (per model and driving state)", min=2)
    rollout_seconds: float = knob(16.0, "length of each long rollout, s", above=0.0)
    clip_frames: int = 16  # Table 1: video frames per FVD clip (FVD16)
    clips_per_rollout: int = 8  # Table 1: FVD clips per long rollout, evenly spaced
    final_frames: int = (
        81  # Table 1: the final chunk, the last this many video frames of a rollout; also the chunk of the per-chunk curve
    )
    fvd_steps: int = knob(20, "sampling steps of the observation models", min=1)
    resamples: int = 200  # clip-bootstrap resamples of every interval
    temperature: float = 0.0  # sampling temperature of every rollout
    # Table 3's state columns and the long-horizon curves: this many long rollouts of this many seconds (None: as
    # ``rollouts`` / ``rollout_seconds``); the first ``rollouts`` of them, cut to ``rollout_seconds``, are the painted
    # ones. State rollouts are cheap and painting is not, so a small protocol can keep Table 3's rules measurable.
    state_rollouts: int | None = knob(
        None, "long rollouts of Table 3's state columns, ≥ --rollouts; the first are painted", min=2
    )
    state_seconds: float | None = knob(None, "their length, s, ≥ --rollout-seconds", above=0.0)

    def __post_init__(self) -> None:
        for f in ("probe_windows", "seed_frames", "horizon", "rollouts", "clip_frames", "clips_per_rollout", "fvd_steps"):
            if not isinstance(getattr(self, f), int) or getattr(self, f) < 1:
                raise ValueError(f"protocol {self.name!r}: {f} is an integer ≥ 1, not {getattr(self, f)!r}")
        if self.rollouts < 2 or self.resamples < 1:
            raise ValueError(
                f"protocol {self.name!r}: FVD needs rollouts ≥ 2 and resamples ≥ 1, not {self.rollouts}, {self.resamples}"
            )
        if self.clip_frames < 3 or self.final_frames < 3:
            raise ValueError(
                f"protocol {self.name!r}: FVD clips hold ≥ 3 frames, not clip_frames={self.clip_frames}, final_frames={self.final_frames}"
            )
        if not self.rollout_seconds > 0 or self.temperature < 0:
            raise ValueError(
                f"protocol {self.name!r}: rollout_seconds > 0 and temperature ≥ 0, not {self.rollout_seconds}, {self.temperature}"
            )
        if self.state_rollouts is not None and (
            not isinstance(self.state_rollouts, int)
            or isinstance(self.state_rollouts, bool)
            or self.state_rollouts < self.rollouts
        ):
            raise ValueError(
                f"protocol {self.name!r}: state_rollouts is an integer ≥ rollouts ({self.rollouts}; the painted rollouts are "
                f"the first of them), not {self.state_rollouts!r}"
            )
        if self.state_seconds is not None and not self.state_seconds >= self.rollout_seconds:
            raise ValueError(
                f"protocol {self.name!r}: state_seconds ≥ rollout_seconds ({self.rollout_seconds:g} s; the painted rollouts "
                f"are their beginnings), not {self.state_seconds!r}"
            )

    @property
    def state_count(self) -> int:
        """Long rollouts of Table 3's state columns (``state_rollouts``, else ``rollouts``)."""
        return self.rollouts if self.state_rollouts is None else self.state_rollouts

    @property
    def state_length_s(self) -> float:
        """Seconds of each of those rollouts (``state_seconds``, else ``rollout_seconds``)."""
        return self.rollout_seconds if self.state_seconds is None else float(self.state_seconds)

    def video_frames(self, video_fps: float) -> int:
        """Video frames T of one long rollout at ``video_fps``, checked to hold every FVD clip and the final chunk."""
        T = int(round(self.rollout_seconds * video_fps))
        if self.final_frames > T or (self.clips_per_rollout - 1) * (T // self.clips_per_rollout) + self.clip_frames > T:
            raise ValueError(
                f"protocol {self.name!r}: a rollout of {self.rollout_seconds:g} s ({T} frames at {video_fps:g} fps) cannot hold "
                f"{self.clips_per_rollout} clips of {self.clip_frames} frames and a final chunk of {self.final_frames}"
            )
        return T

    def clip_starts(self, video_fps: float) -> list[int]:
        """Video frames where Table 1's FVD clips start in a rollout: every T // clips_per_rollout frames from 0."""
        T = self.video_frames(video_fps)
        return [k * (T // self.clips_per_rollout) for k in range(self.clips_per_rollout)]

    def reduced(self) -> list[str]:
        """The counts and lengths where this protocol is smaller than the paper's, as "field value (paper value)"."""
        paper = PROTOCOLS["paper"]
        out = [
            f"{f} {getattr(self, f):g} (paper {getattr(paper, f):g})"
            for f in (
                "probe_windows",
                "seed_frames",
                "horizon",
                "rollouts",
                "rollout_seconds",
                "clip_frames",
                "clips_per_rollout",
                "final_frames",
                "fvd_steps",
                "resamples",
            )
            if getattr(self, f) < getattr(paper, f)
        ]
        for f, mine, theirs in (
            ("state_rollouts", self.state_count, paper.state_count),
            ("state_seconds", self.state_length_s, paper.state_length_s),
        ):
            if mine < theirs:
                out.append(f"{f} {mine:g} (paper {theirs:g})")
        return out

    def to_json(self) -> dict:
        return asdict(self)


PROTOCOLS = {
    "paper": EvalProtocol("paper"),
    # the demo's: inside ~2 minutes of a 10-minute demo on 2 cores
    "quick": EvalProtocol(
        "quick",
        probe_windows=8,
        seed_frames=32,
        horizon=80,
        rollouts=2,
        rollout_seconds=3.0,
        clips_per_rollout=2,
        final_frames=41,
        fvd_steps=4,
        resamples=100,
        state_rollouts=8,  # Table 3's rules need more than 2 × 3 s to show: 8 × 9 s of state cost seconds, unpainted
        state_seconds=9.0,
    ),
}


def parse_protocol(protocol: EvalProtocol | str, **overrides: Any) -> EvalProtocol:
    """A protocol by name (``PROTOCOLS``) or as given, with ``overrides`` of its fields (validated; an unknown field or
    name is a ValueError listing the known ones)."""
    if isinstance(protocol, str):
        if protocol not in PROTOCOLS:
            raise ValueError(f"unknown protocol {protocol!r}; known: {', '.join(PROTOCOLS)}")
        protocol = PROTOCOLS[protocol]
    fields = set(asdict(protocol)) - {"name"}
    if unknown := sorted(set(overrides) - fields):
        raise ValueError(f"protocol options {unknown} are not fields of EvalProtocol ({', '.join(sorted(fields))})")
    if not overrides:
        return protocol
    name = f"{protocol.name} (changed: {', '.join(sorted(overrides))})"
    # more or longer painted rollouts than the named protocol's state rollouts: the state rollouts grow with them
    for painted, state in (("rollouts", "state_rollouts"), ("rollout_seconds", "state_seconds")):
        if painted in overrides and state not in overrides and getattr(protocol, state) is not None:
            overrides[state] = max(getattr(protocol, state), overrides[painted])
    return replace(protocol, name=name, **overrides)
