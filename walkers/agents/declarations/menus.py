"""The readable menus ``conf/algo/<name>.yaml``, written from the declarations in
:mod:`walkers.agents.declarations.schemas` (``make menus``; ``--check``: exit 1 when one is out of
step).

    python -m walkers.agents.declarations.menus [--check]
"""

from __future__ import annotations

import inspect
import sys
from collections.abc import Sequence
from dataclasses import fields
from pathlib import Path

from walkers import PROJECT_ROOT
from walkers.agents.declarations.schemas import SCHEMAS, Hyperparameters

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


def entry(key: str, value: str, doc: str, indent: str = "") -> list[str]:
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
    defaults = schema()
    for f in fields(schema):
        default = getattr(defaults, f.name)
        if f.metadata["follows"]:
            value = "${" + f.metadata["follows"] + "}"
        elif f.metadata["env_key"]:
            fallback = default if isinstance(default, int) else yaml_value(default)
            value = f"${{oc.select:env.{f.metadata['env_key']},{fallback}}}"
        else:
            value = yaml_value(default)
        lines += entry(f.name, value, f.metadata["doc"], indent)
    for key, (value, doc) in schema.RUN_SETTINGS.items():
        lines += entry(key, yaml_value(value), doc)
    return "\n".join(lines) + "\n"


def write_menus(conf_dir=None, check: bool = False) -> list[str]:
    """Write each algorithm's menu ``<conf_dir>/algo/<name>.yaml`` (default: the project's
    ``conf/``) from its declaration; with ``check``, write nothing. Returns the menus that were
    out of step."""
    stale = []
    for name, schema in SCHEMAS.items():
        path = Path(conf_dir or PROJECT_ROOT / "conf") / "algo" / f"{name}.yaml"
        text = menu(schema)
        if not path.is_file() or path.read_text() != text:
            stale.append(str(path))
            if not check:
                path.write_text(text)
    return stale


def main(write, source: str, argv: list[str]) -> int:
    """``make menus``: ``write`` what is written from ``source``; with ``--check``, write nothing
    and exit 1 if something is out of step."""
    checking = "--check" in argv
    stale = write(check=checking)
    for path in stale:
        print(f"{f'out of step with {source}' if checking else 'wrote'}: {path}")
    return 1 if checking and stale else 0


if __name__ == "__main__":  # make menus
    sys.exit(main(write_menus, "walkers/agents/declarations/schemas.py", sys.argv[1:]))
