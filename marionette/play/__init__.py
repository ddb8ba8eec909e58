"""``marionette play``: the world model played in a browser, and the same page as the corpus viewer.

``marionette play RUN CORPUS`` seeds a live rollout of the dynamics checkpoint ``RUN`` from a corpus segment and
serves a page on 127.0.0.1 where keys force action tokens and WASD moves the driven entity's root
(``session.LiveSession``); ``marionette play --replay SOURCE`` plays a corpus segment or a ``STATES.arrow`` through
the bridge with a scrubber (``replay.ReplaySession``). ``server`` is the Starlette app on uvicorn, ``view`` the
bridge's rendering of one frame and the stage map, ``page.html`` the page.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

from marionette.dynamics.controls import parse_rules
from marionette.knobs import add_options, option
from marionette.options import int_in, non_negative_float, non_negative_int, positive_int, size_hxw
from marionette.play.access import access, serve_host, token_value


def port_number(s: str) -> int:
    """An argparse type: a TCP port, 0 (any free port) to 65535."""
    return int_in(0, 65535)(s)


@dataclass(frozen=True, kw_only=True)
class PlayOptions:
    """The play command's options, each checked as it is parsed; ``serve`` takes them as keyword arguments."""

    run: Path | None = option(
        None, "a dynamics checkpoint or training directory (live play)", parse=Path, positional=True, optional=True
    )
    corpus: Path | None = option(
        None, "the corpus whose segment seeds the rollout (live play)", parse=Path, positional=True, optional=True
    )
    replay: Path | None = option(
        None, "replay a corpus directory's segment or a STATES.arrow, no model", parse=Path, metavar="SOURCE"
    )
    replay_corpus: Path | None = option(
        None,
        "replaying a STATES.arrow: the corpus whose vocab names its tokens and whose stage is its terrain",
        parse=Path,
        metavar="CORPUS",
    )
    segment: str | None = option(None, "segment to seed from (live; default the longest held-out one) or to replay")
    port: int = option(8765, "port to serve on (0: any free port)", parse=port_number)
    host: str = option(
        "127.0.0.1",
        "interface to serve on; another than 127.0.0.1 or localhost reaches other machines and needs --token",
        parse=serve_host,
    )
    token: str | None = option(
        None,
        "the secret every request must carry when --host is not loopback (16 or more of A-Z a-z 0-9 _ -, or 'auto' to "
        "draw one); the URL printed at start-up holds it",
        parse=token_value,
    )
    size: tuple[int, int] = option((176, 320), "the view's size, HxW", parse=size_hxw, metavar="HxW")
    fps: float | None = option(
        None,
        "frames per second (default: the model's or the rows' rate; 0: as fast as it can)",
        parse=non_negative_float,
    )
    seed_frames: int = option(64, "recorded frames fed before the first played one", parse=positive_int)
    temperature: float = option(0.0, "sampling temperature of the free entities; 0: argmax", parse=non_negative_float)
    seed: int = option(0, "the sampler's seed", parse=non_negative_int)
    rules: str = option("auto", "rules on at the start: auto, none or a comma list (toggled on the page)", parse=parse_rules)
    record_dir: Path = option(Path("play-sessions"), "where recorded sessions are written", parse=Path)
    paused: bool = option(False, "start paused", switch=True)
    observation: Path | None = option(
        None,
        "paint the live view with this small observation model (its size divides --size), beside the pose view",
        parse=Path,
        metavar="OBS",
    )
    paint_steps: int = option(4, "sampling steps per painted chunk", parse=positive_int)


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The play command's arguments (``PlayOptions``)."""
    add_options(ap, PlayOptions)


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


def serve(
    port: int = 8765, fps: float | None = None, log=print, host: str = "127.0.0.1", token: str | None = None, **session_args
) -> None:
    """Serve the play page on ``host``:``port`` until interrupted (another host than loopback with a token: ``access``)."""
    from .server import Server

    token = access(host, token)  # before the session is made: a missing token costs nothing
    session = make_session(log=log, **session_args)
    server = Server(session, port=port, fps=fps, log=log, host=host, token=token).start()
    log(f"play: {session.kind} session on {' and '.join(server.urls)} (open it in a browser; Ctrl-C stops)")
    try:
        server.wait()
    finally:
        server.stop()
