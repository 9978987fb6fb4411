"""How a hyperparameter is declared: once, with its default, type, allowed values and doc.

Each algorithm's hyperparameters are a dataclass (:mod:`walkers.agents.declarations.schemas`) whose
fields are made by :func:`hp`. Everything else is derived from that one declaration:

- the readable menu ``conf/algo/<name>.yaml`` (:mod:`walkers.agents.declarations.menus`,
  ``make menus``; a test holds it in step with the declarations), each value commented with its
  doc;
- the check of a composed config (:func:`problems`, called by
  ``walkers.training.settings.validate``): a one-line error naming the key, the bad value and
  what is allowed;
- the agent's constructor arguments, which have no defaults of their own
  (:func:`walkers.agents.factory.defaults_for` gives them to code that builds an agent without
  a config, e.g. tests and benchmarks).

Hydra's ConfigStore could hold these dataclasses as the yaml files' schema, but it would reject
a mistyped value while composing, with a multi-line merge error, before walkers sees the config;
checking the composed config here keeps walkers' one-line errors for every key alike.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from numbers import Real
from typing import Any, ClassVar

from walkers.errors import did_you_mean


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
    #: a hyperparameter bounded by another: ``{key: (bound key, why)}`` (key <= bound)
    AT_MOST: ClassVar[dict[str, tuple[str, str]]] = {}
    #: a hyperparameter that must divide another: ``{key: (multiple key, why)}``
    DIVIDES: ClassVar[dict[str, tuple[str, str]]] = {}
    #: values that make a run of a few hundred env steps learn (past any warm-up, several
    #: updates) on small networks: what the tests' tiny runs and the seeded fingerprints use
    TINY: ClassVar[dict[str, Any]] = {}


def tiny_overrides(schema: type[Hyperparameters]) -> list[str]:
    """``schema.TINY`` as command-line overrides: ``["algo.batch_size=32", ...]``."""
    return [f"algo.{key}={_override(value)}" for key, value in schema.TINY.items()]


def _override(value) -> str:
    return "[" + ",".join(map(str, value)) + "]" if isinstance(value, list) else str(value)


def declared(schema: type[Hyperparameters]) -> list[dataclasses.Field]:
    return list(dataclasses.fields(schema))


def defaults(schema: type[Hyperparameters], **overrides) -> dict:
    """The hyperparameters as constructor arguments: the defaults, with ``overrides``."""
    declared_defaults = schema()
    values = {f.name: getattr(declared_defaults, f.name) for f in declared(schema)}
    unknown = set(overrides) - set(values)
    if unknown:
        raise TypeError(f"{schema.NAME} has no hyperparameter {sorted(unknown)[0]!r}")
    return values | overrides


#: Keys of an algorithm's config that are not hyperparameters: what to build, and its name.
NOT_HYPERPARAMETERS = ("_target_", "name")


def problems(schema: type[Hyperparameters], values: dict, prefix: str = "algo.") -> str | None:
    """The first key of ``values`` that is not a declared hyperparameter, or whose value is not
    allowed, as a one-line message; None when all are."""
    names = [f.name for f in declared(schema)]
    for key in values:
        if key not in names and key not in NOT_HYPERPARAMETERS:
            return (
                f"{prefix}{key}={values[key]!r} is not allowed: {schema.NAME} has no "
                f"hyperparameter {key!r} ({did_you_mean(key, names)}it has {', '.join(names)})"
            )
    for f in declared(schema):
        if f.name not in values:
            continue
        value, allowed = values[f.name], f.metadata["allowed"]
        if not allowed.ok(value):
            return f"{prefix}{f.name}={value!r} is not allowed: must be {allowed.text}"
    for key, (bound, why) in schema.AT_MOST.items():
        if key in values and bound in values and values[key] > values[bound]:
            return (
                f"{prefix}{key}={values[key]!r} is not allowed: must be at most "
                f"{prefix}{bound} ({values[bound]}){why}"
            )
    for key, (multiple, why) in schema.DIVIDES.items():
        if key in values and multiple in values and values[multiple] % values[key]:
            return (
                f"{prefix}{key}={values[key]!r} is not allowed: must divide "
                f"{prefix}{multiple} ({values[multiple]}){why}"
            )
    return None
