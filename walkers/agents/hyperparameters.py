"""How a hyperparameter is declared: once, with its default, type, allowed values and doc.

Each algorithm's hyperparameters are a dataclass (:mod:`walkers.agents.schemas`) whose fields are
made by :func:`hp`. Everything else is derived from that one declaration:

- the readable menu ``conf/algo/<name>.yaml`` (written by ``make menus``; a test holds it in
  step with the declarations), each value commented with its doc;
- the check of a composed config (:func:`problems`, called by ``walkers.training.validate``):
  a one-line error naming the key, the bad value and what is allowed;
- the agent's constructor arguments, which have no defaults of their own
  (:func:`defaults` gives them to code that builds an agent without a config, e.g. tests).

Hydra's ConfigStore could hold these dataclasses as the yaml files' schema, but it would reject
a mistyped value while composing, with a multi-line merge error, before walkers sees the config;
checking the composed config here keeps walkers' one-line errors for every key alike.
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from numbers import Real
from typing import Any, ClassVar


@dataclass(frozen=True)
class Allowed:
    """What a hyperparameter may be: a predicate, and its words for the error message."""

    ok: Callable[[Any], bool]
    text: str


def _int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _number(v) -> bool:
    return isinstance(v, Real) and not isinstance(v, bool)


def one_of(*choices: str) -> Allowed:
    return Allowed(lambda v: v in choices, " or ".join(choices))


def or_null(allowed: Allowed, null_means: str = "") -> Allowed:
    meaning = f" ({null_means})" if null_means else ""
    return Allowed(lambda v: v is None or allowed.ok(v), f"null{meaning} or {allowed.text}")


POSITIVE_INT = Allowed(lambda v: _int(v) and v > 0, "an integer > 0")
NON_NEGATIVE_INT = Allowed(lambda v: _int(v) and v >= 0, "an integer >= 0")
POSITIVE = Allowed(lambda v: _number(v) and v > 0, "a number > 0")
NON_NEGATIVE = Allowed(lambda v: _number(v) and v >= 0, "a number >= 0")
NUMBER = Allowed(_number, "a number")
DISCOUNT = Allowed(lambda v: _number(v) and 0 < v <= 1, "a number in (0, 1]")
PROBABILITY = Allowed(lambda v: _number(v) and 0 <= v <= 1, "a number in [0, 1]")
DROPOUT = Allowed(lambda v: _number(v) and 0 <= v < 1, "a number in [0, 1)")
BOOL = Allowed(lambda v: isinstance(v, bool), "true or false")
LAYERS = Allowed(
    lambda v: isinstance(v, list) and len(v) > 0 and all(POSITIVE_INT.ok(x) for x in v),
    "a non-empty list of integers > 0, e.g. [256,256]",
)
NUMBERS = Allowed(
    lambda v: isinstance(v, list) and len(v) > 0 and all(map(_number, v)),
    "a non-empty list of numbers, e.g. [5000,2500]",
)


def hp(default, allowed: Allowed, doc: str, env_key: str | None = None, follows: str = ""):
    """A hyperparameter: its ``default``, what is ``allowed``, its ``doc``.

    ``env_key``: an env config may set it (``conf/env/*.yaml``: ``env.<env_key>``; the menu
    reads ``${oc.select:env.<env_key>,<default>}``). ``follows``: a run setting it always equals
    (the menu reads ``${<follows>}``, e.g. PPO's annealing horizon follows ``total_steps``).
    """
    meta = {"allowed": allowed, "doc": doc, "env_key": env_key, "follows": follows}
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata=meta)
    return field(default=default, metadata=meta)


@dataclass
class Hyperparameters:
    """The base of each algorithm's declaration; ``AGENT`` is the class that takes them."""

    AGENT: ClassVar[str]
    NAME: ClassVar[str]
    #: run settings the algorithm's menu sets too (an offline algorithm counts gradient steps)
    RUN_SETTINGS: ClassVar[dict[str, tuple[Any, str]]] = {}


def declared(schema: type[Hyperparameters]) -> list[dataclasses.Field]:
    return list(dataclasses.fields(schema))


def defaults(schema: type[Hyperparameters], **overrides) -> dict:
    """The hyperparameters as constructor arguments: the defaults, with ``overrides``."""
    values = {f.name: getattr(schema(), f.name) for f in declared(schema)}
    unknown = set(overrides) - set(values)
    if unknown:
        raise TypeError(f"{schema.NAME} has no hyperparameter {sorted(unknown)[0]!r}")
    return values | overrides


def problems(schema: type[Hyperparameters], values: dict, prefix: str = "algo.") -> str | None:
    """The first declared hyperparameter in ``values`` whose value is not allowed, as a
    one-line message; None when all are."""
    for f in declared(schema):
        if f.name not in values:
            continue
        value, allowed = values[f.name], f.metadata["allowed"]
        if not allowed.ok(value):
            return f"{prefix}{f.name}={value!r} is not allowed: must be {allowed.text}"
    return None


# --- the menu: conf/algo/<name>.yaml ------------------------------------------------------------
COMMENT_COLUMN = 25


def yaml_value(value) -> str:
    """``value`` as the menus write it (``3.0e-4``, ``1_000_000``, ``[256, 256]``, ``null``)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return f"{value:_}" if abs(value) >= 10_000 else str(value)
    if isinstance(value, float):
        if value != 0 and abs(value) <= 1e-3:
            mantissa, exponent = f"{value:.1e}".split("e")
            return f"{mantissa}e{int(exponent)}"
        return repr(value)
    if isinstance(value, Sequence) and not isinstance(value, str):
        return "[" + ", ".join(yaml_value(v) for v in value) + "]"
    return str(value)


def _entry(key: str, value: str, doc: str, indent: str = "") -> list[str]:
    head = f"{indent}{key}: {value}"
    lines = doc.split("\n")
    first = f"{head.ljust(COMMENT_COLUMN - 2)}  # {lines[0]}"
    return [first] + [f"{' ' * (COMMENT_COLUMN - 1)} # {line}" for line in lines[1:]]


def menu(schema: type[Hyperparameters]) -> str:
    """The yaml menu of ``schema``: its docstring as the header, then each hyperparameter."""
    header = [f"# {line}".rstrip() for line in inspect.cleandoc(schema.__doc__ or "").split("\n")]
    nested = bool(schema.RUN_SETTINGS)  # a menu that sets run settings: at the config's root
    indent = "  " if nested else ""
    lines = ["# @package _global_"] if nested else []
    lines += [*header, *(["algo:"] if nested else [])]
    lines += [f"{indent}_target_: {schema.AGENT}", f"{indent}name: {schema.NAME}"]
    for f in declared(schema):
        default = getattr(schema(), f.name)
        if f.metadata["follows"]:
            value = "${" + f.metadata["follows"] + "}"
        elif f.metadata["env_key"]:
            fallback = default if isinstance(default, int) else yaml_value(default)
            value = f"${{oc.select:env.{f.metadata['env_key']},{fallback}}}"
        else:
            value = yaml_value(default)
        lines += _entry(f.name, value, f.metadata["doc"], indent)
    for key, (value, doc) in schema.RUN_SETTINGS.items():
        lines += _entry(key, yaml_value(value), doc)
    return "\n".join(lines) + "\n"
