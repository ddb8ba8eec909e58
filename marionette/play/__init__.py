"""``marionette play``: the world model played in a browser, and the same page as the corpus viewer.

``marionette play RUN CORPUS`` seeds a live rollout of the dynamics checkpoint ``RUN`` from a corpus segment and
serves a page on 127.0.0.1 where keys force action tokens and WASD moves the driven entity's root
(``session.LiveSession``); ``marionette play --replay SOURCE`` plays a corpus segment or a ``STATES.arrow`` through
the bridge with a scrubber (``replay.ReplaySession``). ``server`` is the Starlette app on uvicorn, ``view`` the
bridge's rendering of one frame and the stage map, ``page.html`` the page.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from marionette.options import int_in, non_negative_float, non_negative_int, positive_int, size_hxw

ARGUMENTS = (
    "run",
    "corpus",
    "replay",
    "replay_corpus",
    "segment",
    "port",
    "size",
    "fps",
    "seed_frames",
    "temperature",
    "seed",
    "rules",
    "record_dir",
    "paused",
    "observation",
    "paint_steps",
)


def port_number(s: str) -> int:

    return int_in(0, 65535)(s)


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The play command's arguments, each checked as it is parsed."""
    from marionette.dynamics.controls import parse_rules

    ap.add_argument("run", type=Path, nargs="?", help="a dynamics checkpoint or training directory (live play)")
    ap.add_argument("corpus", type=Path, nargs="?", help="the corpus whose segment seeds the rollout (live play)")
    ap.add_argument(
        "--replay",
        type=Path,
        default=None,
        metavar="SOURCE",
        help="replay a corpus directory's segment or a STATES.arrow, no model",
    )
    ap.add_argument(
        "--replay-corpus",
        type=Path,
        default=None,
        metavar="CORPUS",
        help="replaying a STATES.arrow: the corpus whose vocab names its tokens and whose stage is its terrain",
    )
    ap.add_argument("--segment", default=None, help="segment to seed from (live; default the longest held-out one) or to replay")
    ap.add_argument("--port", type=port_number, default=8765, help="port on 127.0.0.1 (0: any free port)")
    ap.add_argument("--size", type=size_hxw, default=(176, 320), metavar="HxW", help="the view's size, HxW")
    ap.add_argument(
        "--fps",
        type=non_negative_float,
        default=None,
        help="frames per second (default: the model's or the rows' rate; 0: as fast as it can)",
    )
    ap.add_argument("--seed-frames", type=positive_int, default=64, help="recorded frames fed before the first played one")
    ap.add_argument(
        "--temperature", type=non_negative_float, default=0.0, help="sampling temperature of the free entities; 0: argmax"
    )
    ap.add_argument("--seed", type=non_negative_int, default=0, help="the sampler's seed")
    ap.add_argument(
        "--rules",
        type=parse_rules,
        default="auto",
        help="rules on at the start: auto, none or a comma list (toggled on the page)",
    )
    ap.add_argument("--record-dir", type=Path, default=Path("play-sessions"), help="where recorded sessions are written")
    ap.add_argument("--paused", action="store_true", help="start paused")
    ap.add_argument(
        "--observation",
        type=Path,
        default=None,
        metavar="OBS",
        help="paint the live view with this small observation model (its size divides --size), beside the pose view",
    )
    ap.add_argument("--paint-steps", type=positive_int, default=4, help="sampling steps per painted chunk")


def make_session(
    run: Path | None,
    corpus: Path | None,
    *,
    replay: Path | None = None,
    replay_corpus: Path | None = None,
    segment: str | None = None,
    size: tuple[int, int] = (176, 320),
    seed_frames: int = 64,
    temperature: float = 0.0,
    seed: int = 0,
    rules: str = "auto",
    record_dir: Path = Path("play-sessions"),
    paused: bool = False,
    observation: Path | None = None,
    paint_steps: int = 4,
    log=print,
):
    """A ``LiveSession`` (``run`` and ``corpus``) or a ``ReplaySession`` (``replay``), the arguments checked together."""
    if replay is not None:
        if observation is not None:
            raise ValueError(
                "--observation paints a live session; a replay has no model (`marionette generate` paints a recording)"
            )
        if run is not None or corpus is not None:
            raise ValueError(
                "--replay plays recorded state with no model: give no RUN or CORPUS (--replay-corpus names a STATES.arrow's)"
            )
        from .replay import ReplaySession

        return ReplaySession(replay, segment=segment, corpus=replay_corpus, size=size, paused=paused, log=log)
    if run is None or corpus is None:
        raise ValueError("live play needs RUN (a dynamics checkpoint) and CORPUS; or replay with --replay SOURCE")
    if replay_corpus is not None:
        raise ValueError("--replay-corpus goes with --replay")
    from .session import LiveSession

    return LiveSession(
        run,
        corpus,
        segment=segment,
        seed_frames=seed_frames,
        size=size,
        temperature=temperature,
        seed=seed,
        rules=rules,
        record_dir=record_dir,
        paused=paused,
        observation=observation,
        paint_steps=paint_steps,
        log=log,
    )


def serve(port: int = 8765, fps: float | None = None, log=print, **session_args) -> None:
    """Serve the play page on 127.0.0.1:``port`` until interrupted."""
    from .server import Server

    session = make_session(log=log, **session_args)
    server = Server(session, port=port, fps=fps, log=log).start()
    log(f"play: {session.kind} session on {server.url} (open it in a browser; Ctrl-C stops)")
    try:
        server.wait()
    finally:
        server.stop()
