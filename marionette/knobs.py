"""A config's knobs and the flags made from them: a config is a frozen dataclass whose fields are ``knob``s (a
default, a help text, the values it accepts); ``check_knobs`` enforces them on a config, ``add_config_arguments``
makes one validated flag per field, and ``add_training_arguments`` adds a training command's corpus, output,
process and node options. Importable without torch: a command's ``--help`` reads it."""

from __future__ import annotations

import argparse
import json
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import MISSING, field, fields
from pathlib import Path
from typing import Any

from marionette.distributed import Nodes, host_problem, nodes_problem, port_problem
from marionette.options import Parser


def knob(
    default: Any,
    help: str,
    *,
    choices: Sequence[Any] | None = None,
    min: float | None = None,
    max: float | None = None,
    above: float | None = None,
    below: float | None = None,
) -> Any:
    """A config field with its help text and the values it accepts (``choices``; ``min`` ≤ v ≤ ``max``,
    ``above`` < v < ``below``, each element of a tuple); ``check_knobs`` and the flags of
    ``add_config_arguments`` both enforce them."""
    limits = {"choices": choices, "min": min, "max": max, "above": above, "below": below}
    return field(default=default, metadata={"help": help, **limits})


def knob_problem(f: Any, value: Any) -> str | None:
    """What is wrong with ``value`` for the knob ``f`` (a dataclass field), or None; None is accepted where
    the default is None."""
    m = f.metadata
    if value is None and f.default is None:
        return None
    if m.get("choices") is not None and value not in m["choices"]:
        return f"{value!r} is not one of {list(m['choices'])}"
    for v in value if isinstance(value, tuple) else (value,):
        if not isinstance(v, int | float) or isinstance(v, bool):
            continue
        if m.get("min") is not None and v < m["min"]:
            return f"must be at least {m['min']}, not {v}"
        if m.get("max") is not None and v > m["max"]:
            return f"must be at most {m['max']}, not {v}"
        if m.get("above") is not None and v <= m["above"]:
            return f"must be greater than {m['above']}, not {v}"
        if m.get("below") is not None and v >= m["below"]:
            return f"must be less than {m['below']}, not {v}"
    return None


def check_knobs(config: Any) -> None:
    """Fail, naming the field, on a value its knob does not accept."""
    for f in fields(config):
        problem = knob_problem(f, getattr(config, f.name))
        if problem:
            what = re.split(r" \(|;", f.metadata.get("help", ""), maxsplit=1)[0]  # the help's first clause says what it is
            raise ValueError(f"{type(config).__name__}.{f.name}{f' ({what})' if what else ''}: {problem}")


def _flag_type(kind: type, problem: Callable[[Any], str | None]) -> Callable[[str], Any]:
    """An argparse type: ``kind`` of the text, refused (exit 2, the problem named) where ``problem`` says so."""

    def parse(s: str) -> Any:
        try:
            v = kind(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, not {s!r}") from None
        if kind is float and not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"expected a finite number, not {s!r}")
        if (why := problem(v)) is not None:
            raise argparse.ArgumentTypeError(why)
        return v

    return parse


def add_config_arguments(ap: argparse.ArgumentParser, cls: type) -> None:
    """One flag per field of the config dataclass ``cls`` (``--batch-size`` for ``batch_size``), its help
    text ending in the default; every flag defaults to None, so ``config_from_args`` sees which were given."""
    for f in fields(cls):
        flag = "--" + f.name.replace("_", "-")
        text = f.metadata.get("help", "")
        if f.default is not None and f.default is not MISSING:
            shown = " ".join(map(str, f.default)) if isinstance(f.default, tuple) else str(f.default)
            text += f" (default: {shown})"
        text = text.replace("%", "%%")
        kind = str(f.type).removesuffix(" | None")
        if kind == "bool":
            ap.add_argument(flag, action=argparse.BooleanOptionalAction, default=None, help=text)
        elif kind == "str":
            ap.add_argument(flag, choices=f.metadata.get("choices"), default=None, help=text)
        elif kind in ("int", "float"):
            check = _flag_type(int if kind == "int" else float, lambda v, f=f: knob_problem(f, v))
            ap.add_argument(flag, type=check, default=None, help=text, metavar=f.name.upper())
        elif kind == "tuple[float, float]":
            check = _flag_type(float, lambda v, f=f: knob_problem(f, v))
            ap.add_argument(flag, type=check, nargs=2, default=None, help=text, metavar=("A", "B"))
        else:
            raise TypeError(f"{cls.__name__}.{f.name}: no flag for a field of type {f.type}")


def nodes_from_args(args: argparse.Namespace) -> Nodes:
    """The ``Nodes`` of parsed node options."""
    return Nodes(args.nnodes, args.node_rank, args.master_addr, args.master_port)


def config_from_args(cls: type, args: argparse.Namespace) -> Any:
    """The config of parsed arguments: the ``--config`` JSON when given, then the flags that were given."""
    base = {}
    if getattr(args, "config", None):
        try:
            base = cls.from_json(json.loads(Path(args.config).read_text())).to_json()
        except (json.JSONDecodeError, TypeError, ValueError) as exc:
            raise ValueError(f"{args.config}: not a {cls.__name__} JSON: {exc}") from exc
    over = {f.name: getattr(args, f.name) for f in fields(cls) if getattr(args, f.name, None) is not None}
    return cls.from_json({**base, **over})


def _host(s: str) -> str:
    """An argparse type: a host name or an IP address (``distributed.host_problem``)."""
    if (why := host_problem(s)) is not None:
        raise argparse.ArgumentTypeError(why)
    return s


def add_training_arguments(ap: Parser, cls: type) -> None:
    """A training command's arguments: the corpus, ``--out``, ``--config``, one flag per field of ``cls``,
    ``--nproc``, the node options (``--nnodes``, ``--node-rank``, ``--master-addr``, ``--master-port``,
    checked together once parsed) and ``--progress``."""
    ap.add_argument("corpus", type=Path, help="the corpus directory")
    ap.add_argument("--out", type=Path, required=True, help="training directory (checkpoints; a rerun resumes from it)")
    ap.add_argument("--config", type=Path, help=f"a JSON of {cls.__name__} fields; the flags below override it")
    add_config_arguments(ap, cls)
    at_least_one = _flag_type(int, lambda v: None if v >= 1 else f"must be at least 1, not {v}")
    ap.add_argument(
        "--nproc",
        type=at_least_one,
        default=1,
        metavar="N",
        help="processes on this machine: > 1 relaunches this command under torchrun (DDP) (default: %(default)s)",
    )
    nodes = ap.add_argument_group(
        "several machines",
        "one command per machine, the same but for --node-rank; OUT (and the corpus) on a filesystem they all share",
    )
    nodes.add_argument("--nnodes", type=at_least_one, default=1, metavar="N", help="machines of the run (default: %(default)s)")
    nodes.add_argument(
        "--node-rank",
        type=_flag_type(int, lambda v: None if v >= 0 else f"must be at least 0, not {v}"),
        default=0,
        metavar="R",
        help="this machine's rank, 0 to N - 1; node 0 hosts the rendezvous and its first process writes OUT (default: %(default)s)",
    )
    nodes.add_argument("--master-addr", type=_host, metavar="HOST", help="node 0's host name or IP address (with --nnodes > 1)")
    nodes.add_argument(
        "--master-port", type=_flag_type(int, port_problem), metavar="PORT", help="a free TCP port on node 0 (with --nnodes > 1)"
    )
    ap.add_check(lambda a: nodes_problem(a.nnodes, a.node_rank, a.master_addr, a.master_port))
    ap.add_argument(
        "--progress",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="a progress bar over the training steps (default: on)",
    )
