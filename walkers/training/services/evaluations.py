"""Every ``eval_every`` steps and at the last: the run's evaluation, and what reads it (a sweep's
pruner)."""

from __future__ import annotations

from collections.abc import Callable

from walkers.training.services.service import RunService


class Evaluations(RunService):
    """The book's evaluation (greedy episodes, or an offline run's normalized score): ``eval/*``
    logged, ``best.pt`` on a new best, and a flush, so the curves move in the UI."""

    def every(self, settings) -> int:
        return settings.eval_every

    def after_step(self, book, losses) -> bool:
        p, s = book.progress, book.settings
        if p.step % s.eval_every == 0 or p.step == s.total_steps:
            returns, extra = book.evaluation(book.agent, book.eval_env, book.eval_start_seeds)
            mean = float(returns.mean())
            p.eval_steps.append(p.step)
            p.eval_means.append(mean)
            metrics = {"eval/return_mean": mean, "eval/return_std": float(returns.std())}
            book.run.log_metrics(metrics | extra, p.step)
            if mean > p.best_eval:
                p.best_eval = mean
                book.save_checkpoint("best.pt")
            book.run.flush()
        return False


class Pruning(RunService):
    """After an evaluation before the budget's end: ``on_evaluation(step, eval mean)`` (a sweep
    trial's pruner) True stops the run early (a finished run is never "stopped early")."""

    def __init__(self, on_evaluation: Callable[[int, float], bool]):
        self.on_evaluation = on_evaluation

    def every(self, settings) -> int:
        return settings.eval_every

    def after_step(self, book, losses) -> bool:
        p = book.progress
        if p.eval_steps[-1:] != [p.step] or p.step >= book.settings.total_steps:
            return False
        if self.on_evaluation(p.step, p.eval_means[-1]):
            book.stopped_early = True
            return True
        return False
