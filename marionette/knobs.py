"""A config's knobs and the flags made from them: a config is a frozen dataclass whose fields are ``knob``s (a
default, a help text, the values it accepts); ``check_knobs`` enforces them on a config, ``add_config_arguments``
makes one validated flag per field, and ``add_training_arguments`` adds a training command's corpus, output,
process and node options. A command's own options are a dataclass of ``option`` fields (each with its checked type,
flag and help): ``add_options`` adds them to its parser and ``options_from_args`` reads them back, so the flags and the
call they feed are one list. Importable without torch: a command's ``--help`` reads it."""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import MISSING, field, fields
from pathlib import Path
from typing import Any

from marionette.distributed import Nodes, host_problem, nodes_problem, port_problem
from marionette.io import read_json
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
    flag: str | None = None,
) -> Any:
    """A config field with its help text and the values it accepts (``choices``; ``min`` ≤ v ≤ ``max``,
    ``above`` < v < ``below``, each element of a tuple); ``check_knobs`` and the flags of
    ``add_config_arguments`` both enforce them. ``flag``: its command-line flag where it is not the field's name
    (``--batch-size`` for ``batch_size``)."""
    limits = {"choices": choices, "min": min, "max": max, "above": above, "below": below}
    return field(default=default, metadata={"help": help, **limits, **({"flag": flag} if flag else {})})


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


def add_config_arguments(
    ap: argparse.ArgumentParser, cls: type, names: Sequence[str] | None = None, default: str | None = None
) -> None:
    """One flag per field of the config dataclass ``cls`` (``--batch-size`` for ``batch_size``, or the knob's
    ``flag``), or per field in ``names``, its help text ending in the default (``default``: the words shown
    instead, e.g. "the protocol's"); every flag defaults to None, so ``config_from_args`` sees which were given."""
    chosen = [f for f in fields(cls) if names is None or f.name in names]
    if names is not None and len(chosen) != len(names):
        raise TypeError(f"{cls.__name__} has no fields {sorted(set(names) - {f.name for f in chosen})}")
    for f in chosen:
        flag = f.metadata.get("flag") or "--" + f.name.replace("_", "-")
        text = f.metadata.get("help", "")
        if default is not None:
            text += f" (default: {default})"
        elif f.default is not None and f.default is not MISSING:
            shown = " ".join(map(str, f.default)) if isinstance(f.default, tuple) else str(f.default)
            text += f" (default: {shown})"
        text = text.replace("%", "%%")
        kind = str(f.type).removesuffix(" | None")
        common = {"dest": f.name, "default": None, "help": text}
        if kind == "bool":
            ap.add_argument(flag, action=argparse.BooleanOptionalAction, **common)
        elif kind == "str":
            ap.add_argument(flag, choices=f.metadata.get("choices"), **common)
        elif kind in ("int", "float"):
            check = _flag_type(int if kind == "int" else float, lambda v, f=f: knob_problem(f, v))
            ap.add_argument(flag, type=check, metavar=f.name.upper(), **common)
        elif kind == "tuple[float, float]":
            check = _flag_type(float, lambda v, f=f: knob_problem(f, v))
            ap.add_argument(flag, type=check, nargs=2, metavar=("A", "B"), **common)
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
            base = cls.from_json(read_json(Path(args.config))).to_json()
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{args.config}: not a {cls.__name__} JSON: {exc}") from exc
    over = {f.name: getattr(args, f.name) for f in fields(cls) if getattr(args, f.name, None) is not None}
    return cls.from_json({**base, **over})


def option(
    default: Any,
    help: str,
    *,
    parse: Callable[[str], Any] | None = None,
    flag: str | None = None,
    metavar: str | None = None,
    positional: bool = False,
    many: bool = False,
    switch: bool = False,
    optional: bool = False,
    choices: Sequence[str] | None = None,
    append: bool = False,
    group: tuple[str, str] | None = None,
) -> Any:
    """A command's option as a dataclass field: its default (``MISSING``: required), help, the argparse type that
    checks it as it is parsed (``parse``), its flag (default ``--`` and the field's name with dashes), ``metavar``;
    ``positional`` (``optional``: it may be left out), ``many`` (repeatable, each flag taking one or more values,
    gathered into a tuple), ``switch`` (a flag without a value: it sets True, or False where the default is True,
    e.g. ``--no-pose``), ``choices`` (the values it accepts), ``append`` (repeatable, one value a flag, gathered
    into a tuple), ``group`` (the help's group of options it is listed in: title, description)."""
    spec = {"parse": parse, "flag": flag, "metavar": metavar, "positional": positional, "many": many, "switch": switch}
    spec |= {"optional": optional, "choices": choices, "append": append, "group": group}
    return field(default=default, metadata={"help": help, "option": spec})


def add_options(ap: argparse.ArgumentParser, cls: type, defaults: dict[str, Any] | None = None) -> None:
    """Add the ``option`` fields of the dataclass ``cls`` to ``ap``, in field order, each with its default (or the one
    ``defaults`` gives it: options shared by two commands with defaults of their own)."""
    defaults = defaults or {}
    if unknown := set(defaults) - {f.name for f in fields(cls)}:
        raise TypeError(f"{cls.__name__} has no fields {sorted(unknown)}")
    groups: dict[str, Any] = {}
    for f in fields(cls):
        if "option" not in f.metadata:
            raise TypeError(f"{cls.__name__}.{f.name} is not an option (knobs.option)")
        spec = f.metadata["option"]
        target = ap
        if spec["group"] is not None:
            title, description = spec["group"]
            if title not in groups:
                groups[title] = ap.add_argument_group(title, description)
            target = groups[title]
        kwargs: dict[str, Any] = {"help": f.metadata["help"]}
        if spec["metavar"]:
            kwargs["metavar"] = spec["metavar"]
        if spec["choices"]:
            kwargs["choices"] = spec["choices"]
        if spec["positional"]:
            if spec["optional"]:
                kwargs["nargs"] = "?"
            target.add_argument(f.name, type=spec["parse"], **kwargs)
            continue
        flag = spec["flag"] or "--" + f.name.replace("_", "-")
        if spec["switch"]:
            target.add_argument(flag, dest=f.name, action="store_false" if f.default is True else "store_true", **kwargs)
        elif spec["many"]:
            target.add_argument(flag, dest=f.name, type=spec["parse"], nargs="+", action="extend", default=[], **kwargs)
        elif spec["append"]:
            target.add_argument(flag, dest=f.name, type=spec["parse"], action="append", default=[], **kwargs)
        elif f.default is MISSING:
            target.add_argument(flag, dest=f.name, type=spec["parse"], required=True, **kwargs)
        else:
            target.add_argument(flag, dest=f.name, type=spec["parse"], default=defaults.get(f.name, f.default), **kwargs)


def options_from_args(cls: type, args: argparse.Namespace) -> Any:
    """The ``cls`` of parsed arguments (``add_options``'s): repeatable options as tuples."""
    return cls(**{f.name: _frozen(getattr(args, f.name)) for f in fields(cls)})


def option_values(options: Any) -> dict[str, Any]:
    """An options dataclass's fields by name, unconverted (the keyword arguments of the function it feeds)."""
    return {f.name: getattr(options, f.name) for f in fields(options)}


def _frozen(v: Any) -> Any:
    return tuple(v) if isinstance(v, list) else v


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
