"""How every report writes its numbers: the one place a number, a CI, a count of runs, the
CPU-hours and a markdown table's header are spelled (the comparison's report, the suite report
and an A/B study's ledger)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable


def number(x: float | None) -> str:
    """Three significant digits, whole numbers from 100 on (``1,234``); ``n/a`` for none."""
    if x is None or not math.isfinite(x):
        return "n/a"
    return f"{x:,.0f}" if abs(x) >= 100 else f"{x:.3g}"


def one_decimal(x: float) -> str:
    """Normalized scores (percent of the reference): one decimal."""
    return f"{x:.1f}"


def interval(
    point: float, low: float, high: float, written: Callable[[float], str] = number
) -> str:
    """``point [low, high]``, each ``written`` so; a CI too few seeds allow is said."""
    if math.isnan(low):
        return f"{written(point)} (too few seeds for a CI)"
    return f"{written(point)} [{written(low)}, {written(high)}]"


def runs(n: int) -> str:
    return f"{n} run" if n == 1 else f"{n} runs"


def cpu_hours(hours: float, counted: int, of: int, digits: str = ".3g") -> str:
    """CPU-hours summed over runs, ``-`` when none counted them, and how many did when not all
    (a run from before the count, or resumed from one)."""
    if not counted:
        return "-"
    return f"{hours:{digits}}" + (f" ({counted} of {of} runs counted)" if counted < of else "")


def header(first: str, columns: Iterable[str]) -> list[str]:
    """A markdown table's first two lines."""
    columns = [first, *columns]
    return ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
