"""The relay every painter shares (``generate``, ``marionette play``'s painter, the evaluation's clips): a video
longer than one chunk is made chunk by chunk; chunk k + 1 takes the last painted frame of chunk k as its first frame
and the next T − 1 control frames, so N chunks yield 1 + N·(T − 1) frames (``marionette.chunks``). Noise comes from
one ``torch.Generator`` seeded by ``seed``: the same seed gives the same video."""

from __future__ import annotations

import torch
from torch import Tensor

from marionette.chunks import relay_chunks, relay_frames, relay_step
from marionette.observation.model import VideoDiT, check_inputs, sample_chunk
from marionette.observation.references import EntityReferences


class Relay:
    """A relayed generation fed one chunk's control at a time (``paint``): each chunk starts from the last frame of the
    one before (the given first frame for the first; noised at ``handoff_level`` for a model trained with
    ``handoff_noise``), and a model with reference slots is given, at every chunk, each
    entity's crop from the frames so far (``observation.references``: the first that showed it, retaken as it shows
    larger, but a look the given frame showed never from a painted frame; ``references=False``: none).
    ``generate`` runs it over a whole control; ``marionette play`` over live pose frames as they come."""

    def __init__(
        self,
        model: VideoDiT,
        first: Tensor,
        first_control: Tensor,
        steps: int = 20,
        seed: int = 0,
        references: bool = True,
        handoff: float | None = None,
    ) -> None:
        self.model, self.steps = model.eval(), int(steps)
        self.handoff = model.config.handoff_level if handoff is None else float(handoff)
        if not 0 <= self.handoff <= 2 or (self.handoff and not model.config.handoff_noise):
            raise ValueError(f"hand-off noise {self.handoff}: a σ within [0, 2], for a model trained with handoff_noise")
        self.cur = first  # (3, H, W): the frame the next chunk starts from
        self.generator = torch.Generator().manual_seed(int(seed))
        self.painted = 1  # frames so far, the first included
        self.seen = None
        c = model.config
        if c.references and references:
            self.seen = EntityReferences(c.reference_bands, c.reference_size)
            self.seen.see(first[None], first_control[None])

    def paint(self, control: Tensor) -> Tensor:
        """The chunk of ``control`` (T, ...) whose frame 0 is the current frame: its T − 1 new frames (T − 1, 3, H, W)."""
        refs = self.seen.tensor()[None].to(self.cur.device) if self.seen is not None else None
        first, level = self.cur[None], None
        if self.handoff and self.painted > 1:  # a frame the model painted: given noised, as the model was trained to take it
            noise = torch.randn(first.shape, generator=self.generator).to(first.device)
            first, level = first + self.handoff * noise, torch.full((1,), self.handoff, device=first.device)
        clip = sample_chunk(self.model, control[None], first, self.steps, self.generator, refs, level)[0]
        if self.seen is not None:
            self.seen.see(clip[1:], control[1:], offset=self.painted, painted=True)
        self.cur = clip[-1]
        self.painted += len(clip) - 1
        return clip[1:]


def generate(
    model: VideoDiT,
    control: Tensor,
    first: Tensor,
    chunks: int | None = None,
    steps: int = 20,
    seed: int = 0,
    references: bool = True,
    handoff: float | None = None,
) -> Tensor:
    """RGB video (1 + N·(T − 1), 3, H, W) in [−1, 1] from a control (a pose video, or the baseline's action
    schedule, ≥ that many frames) and a first frame, relayed over N chunks (default: as many as it holds; ``Relay``:
    the references and the hand-off noise, ``handoff``: its σ instead of the model's ``handoff_level``)."""
    c = model.config
    check_inputs(c, control, first)
    step = relay_step(c.frames)
    n = relay_chunks(len(control), c.frames) if chunks is None else int(chunks)
    if n < 1 or relay_frames(n, c.frames) > len(control):
        raise ValueError(f"{n} chunks need {relay_frames(n, c.frames)} control frames; the control has {len(control)}")
    relay = Relay(model, first, control[0], steps, seed, references, handoff)
    out = [first[None]] + [relay.paint(control[k * step : k * step + c.frames]) for k in range(n)]
    return torch.cat(out, dim=0)
