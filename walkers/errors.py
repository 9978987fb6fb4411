"""Errors the command-line entrypoints turn into one clear line and exit code 2."""

from __future__ import annotations

import difflib
from collections.abc import Iterable


class ConfigError(ValueError):
    """A value that cannot work; the message names the key, the bad value and what is allowed."""


class CheckpointError(RuntimeError):
    """A checkpoint that is missing, truncated or corrupted; the message names the file."""


def did_you_mean(given: str, allowed: Iterable[str]) -> str:
    """``"did you mean 'x'? "`` for the allowed names closest to a mistyped one, else ``""``:
    the two closest of those alike by 0.7 (difflib's ratio), else one with the same letters in
    another order (a swapped pair in a short name: ``evn`` for ``env``, which difflib rates
    0.67, as it does ``a2c`` against ``sac``)."""
    allowed = list(allowed)
    close = (
        difflib.get_close_matches(given, allowed, n=2, cutoff=0.7)
        or [name for name in allowed if sorted(name) == sorted(given)][:1]
    )
    return f"did you mean {' or '.join(repr(c) for c in close)}? " if close else ""
