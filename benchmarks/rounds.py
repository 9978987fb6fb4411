"""What every benchmark here shares: contenders take turns, the table shows medians and ratios."""

from __future__ import annotations

import statistics
from collections.abc import Callable


def alternate(contenders: dict, measure: Callable, reps: int) -> dict[str, list[float]]:
    """``reps`` rounds in which each contender is measured once, in turn (noise hits all alike)."""
    results = {name: [] for name in contenders}
    for _ in range(reps):
        for name, contender in contenders.items():
            results[name].append(measure(contender))
    return results


def print_table(results: dict[str, list[float]], unit: str, baseline: str) -> None:
    """Markdown table: median, best round, median / the baseline's median (n/a without it)."""
    base = statistics.median(results[baseline]) if baseline in results else None
    best = min if "ms" in unit else max  # for times lower is better, for rates higher
    label = f"ratio to {baseline}"
    width = max(18, *(len(name) for name in results))
    print(f"| {'implementation':<{width}} | {unit:>11} | {'best':>7} | {label} |")
    print(f"|{'-' * (width + 2)}|{'-' * 13}|{'-' * 9}|{'-' * (len(label) + 2)}|")
    for name, values in results.items():
        median = statistics.median(values)
        ratio = f"{median / base:.2f}" if base else "n/a"
        print(
            f"| {name:<{width}} | {median:>11.2f} | {best(values):>7.2f} | {ratio:>{len(label)}} |"
        )
