"""Where a study stands: from its finished seeds, each question's answer and the seeds still
needed. A pure function of the scores, so a study interrupted anywhere needs no state of its
own: the same scores give the same answers, the same next round."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from walkers.ab.spec import Scores, StudySpec
from walkers.analysis.sequential import (
    Question,
    answer,
    next_look_seeds,
    suite_scores,
)
from walkers.metrics import normalized_score

#: Finished scores: (arm, env) -> {seed: score}


@dataclass
class Standing:
    """The study after the seeds at hand: every question answered or open, and the jobs left."""

    questions: list[Question]
    needed: dict[tuple[str, str], int]  # (arm, env) -> seeds it must have for the next looks
    normalized: dict[tuple[str, str], list[float]]  # per (arm, env), in seed order

    @property
    def look(self) -> int:
        """The latest look any question reached (0-based; -1: none yet)."""
        return max(q.answer.look for q in self.questions)

    def missing(self, scores: Scores) -> list[tuple[str, str, int]]:
        """The jobs to run next: (arm, env, seed) needed and not finished."""
        return [
            (arm, env, seed)
            for (arm, env), n in self.needed.items()
            for seed in range(n)
            if seed not in scores.get((arm, env), {})
        ]


def contiguous(by_seed: Mapping[int, float]) -> list[float]:
    """Scores of seeds 0, 1, ... up to the first one missing: the seeds a look may use."""
    out = []
    while len(out) in by_seed:
        out.append(by_seed[len(out)])
    return out


def standing(spec: StudySpec, scores: Scores) -> Standing:
    design = spec.design()
    norm = {
        (arm.name, env): [
            normalized_score(s, spec.scores[env].random, spec.scores[env].reference)
            for s in contiguous(scores.get((arm.name, env), {}))
        ]
        for arm in spec.arms
        for env in spec.envs
    }
    needed = {key: design.looks[0] for key in norm}
    questions = spec.questions()
    for q in questions:
        if q.env is not None:
            a, b = norm[(q.a, q.env)], norm[(q.b, q.env)]
            envs = [q.env]
        else:  # the aggregate: per seed, the mean normalized score over the envs
            a = suite_scores({env: norm[(q.a, env)] for env in spec.envs})
            b = suite_scores({env: norm[(q.b, env)] for env in spec.envs})
            envs = list(spec.envs)
        q.answer = answer(a, b, design)
        want = next_look_seeds(q.answer, design)
        for arm in (q.a, q.b):
            for env in envs:
                needed[(arm, env)] = max(needed[(arm, env)], want)
    return Standing(questions, needed, norm)
