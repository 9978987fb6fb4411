"""An A/B study's declaration (a file in ``conf/ab/``, read by the sweeper), checked in one line.

A study file sets ``hydra.sweeper`` to :class:`StudySpec`'s fields::

    name: locomotion
    arms: {td3: algo=td3, sac: algo=sac, td3_wide: "algo=td3 algo.hidden_sizes=[400,300]"}
    envs: [walker2d, hopper]
    seeds: {min: 5, max: 15, per_round: 2}
    score: final/return_mean
    alpha: 0.05
    smallest_difference: 10     # normalized points (100 = the env's reference above random)

and the run settings every arm shares (``total_steps``, ``eval_every``, ...) at the top level.
"""

from __future__ import annotations

import itertools
import re
import shlex
from collections.abc import Mapping
from dataclasses import dataclass

import yaml
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import OverrideParseException

from walkers import CONF_DIR
from walkers.analysis.sequential import Design, Question
from walkers.errors import ConfigError
from walkers.tracking.names import study_job_key, study_jobs_prefix, study_of_job_key

#: A study's finished scores: (arm, env) -> {seed: score}, as its rounds read them.
Scores = Mapping[tuple[str, str], Mapping[int, float]]

#: Scores a study may decide on (the aggregate averages normalized returns).
SCORES = ("final/return_mean", "final/return_last10", "final/auc")
_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


@dataclass(frozen=True)
class Arm:
    """One configuration: a name and the overrides that make it; or a reference arm, whose
    seeds come from a results bundle (``reference``; ``of``: the arm of the study that made
    it, where the bundle holds several) and are never trained."""

    name: str
    overrides: tuple[str, ...]
    reference: str | None = None
    of: str | None = None

    def describe(self) -> str:
        if self.reference:
            return f"reference {self.reference}" + (f" (arm {self.of})" if self.of else "")
        return " ".join(self.overrides)


@dataclass(frozen=True)
class EnvScores:
    """An env's normalization: 0 is a uniform random policy, 100 the reference score."""

    random: float
    reference: float


@dataclass(frozen=True)
class StudySpec:
    name: str
    arms: tuple[Arm, ...]
    envs: tuple[str, ...]
    seeds_min: int
    seeds_max: int
    per_round: int
    score: str
    alpha: float
    smallest_difference: float
    scores: Mapping[str, EnvScores]

    @classmethod
    def parse(cls, name, arms, envs, seeds, score, alpha, smallest_difference) -> StudySpec:
        """The declaration as the sweeper got it; :class:`ConfigError` names the bad value."""
        if not isinstance(name, str) or not _NAME.match(name):
            raise ConfigError(
                f"hydra.sweeper.name={name!r} is not allowed: a study name of letters, digits, "
                "'_', '.' or '-' (set it in the study file)"
            )
        parsed_arms = _arms(arms)
        env_names = _envs(envs)
        seeds = dict(seeds or {})
        unknown = set(seeds) - {"min", "max", "per_round"}
        if unknown:
            raise ConfigError(
                f"hydra.sweeper.seeds has {sorted(unknown)}: allowed keys are min, max, per_round"
            )
        low, high, per_round = (seeds.get(k) for k in ("min", "max", "per_round"))
        for key, value in (("min", low), ("max", high), ("per_round", per_round)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ConfigError(
                    f"hydra.sweeper.seeds.{key}={value!r} is not allowed: an integer >= 1"
                )
        if low < 2:
            raise ConfigError(
                f"hydra.sweeper.seeds.min={low} is not allowed: at least 2 seeds per arm"
            )
        if high < low:
            raise ConfigError(
                f"hydra.sweeper.seeds.max={high} is not allowed: at least seeds.min={low}"
            )
        if score not in SCORES:
            raise ConfigError(
                f"hydra.sweeper.score={score!r} is not allowed: must be one of {', '.join(SCORES)}"
            )
        if not isinstance(alpha, int | float) or isinstance(alpha, bool) or not 0 < alpha < 1:
            raise ConfigError(
                f"hydra.sweeper.alpha={alpha!r} is not allowed: must be a number in (0, 1)"
            )
        if (
            not isinstance(smallest_difference, int | float)
            or isinstance(smallest_difference, bool)
            or smallest_difference < 0
        ):
            raise ConfigError(
                f"hydra.sweeper.smallest_difference={smallest_difference!r} is not allowed: a "
                "number >= 0, in normalized points (100 = the env's reference score above random)"
            )
        return cls(
            name,
            parsed_arms,
            env_names,
            low,
            high,
            per_round,
            score,
            float(alpha),
            float(smallest_difference),
            {env: env_scores(env) for env in env_names},
        )

    # --- what follows from it -----------------------------------------------------------------
    @property
    def suite(self) -> bool:
        """Several envs: the aggregate over them is asked too."""
        return len(self.envs) > 1

    def questions(self) -> list[Question]:
        """Each pair of arms on each env, and on the aggregate when there are several envs."""
        pairs = list(itertools.combinations([arm.name for arm in self.arms], 2))
        places = list(self.envs) + ([None] if self.suite else [])
        return [Question(a, b, env) for env in places for a, b in pairs]

    def design(self) -> Design:
        return self._design(len(self.questions()))

    def checked_design(self) -> Design:
        """The design, refused in one line when no look of it can answer "better" whatever the
        returns (the rank test's smallest p never reaches a look's level): such a study would
        spend its whole budget to end "not settled". The line names the fewest ``seeds.max``
        that could decide, and the most questions that could at this maximum."""
        design = self.design()
        if design.deciding_looks():
            return design
        questions = len(self.questions())
        fewest_max = next(
            high
            for high in itertools.count(self.seeds_max + 1)
            if self._design(questions, high).deciding_looks()
        )
        most_questions = next(
            (q for q in range(questions - 1, 0, -1) if self._design(q).deciding_looks()), None
        )
        fewer = (
            f", or ask at most {most_questions} question{'s' * (most_questions > 1)} (fewer "
            "arms or envs)"
            if most_questions
            else ""
        )
        raise ConfigError(
            f"study {self.name!r}: with {questions} question{'s' * (questions > 1)} and at most "
            f"{self.seeds_max} seeds per arm no look can reach its level (the fewest that can: "
            f"{fewest_max}); raise hydra.sweeper.seeds.max{fewer}"
        )

    def _design(self, questions: int, seeds_max: int | None = None) -> Design:
        return Design.of(
            self.alpha,
            questions,
            self.seeds_min,
            seeds_max or self.seeds_max,
            self.per_round,
            self.smallest_difference,
        )

    @property
    def trained_arms(self) -> tuple[Arm, ...]:
        """The arms the study trains: all but its reference arms."""
        return tuple(arm for arm in self.arms if arm.reference is None)

    def arm(self, name: str) -> Arm:
        return next(arm for arm in self.arms if arm.name == name)

    def job_key(self, arm: str, env: str, seed: int) -> str:
        return study_job_key(self.name, arm, env, seed)

    @property
    def job_key_prefix(self) -> str:
        return study_jobs_prefix(self.name)

    def parse_job_key(self, key: str) -> tuple[str, str, int] | None:
        """``(arm, env, seed)`` of one of this study's job keys, else None."""
        place = study_of_job_key(key)
        if place is None or place[0] != self.name:
            return None
        return place[1:]

    def design_params(self) -> dict[str, str]:
        """What fixes the study's test: logged once as params, refused if a rerun differs."""
        return {
            "ab.arms": ", ".join(f"{a.name}: {a.describe()}" for a in self.arms),
            "ab.envs": ",".join(self.envs),
            "ab.seeds": f"min={self.seeds_min} max={self.seeds_max} per_round={self.per_round}",
            "ab.score": self.score,
            "ab.alpha": repr(self.alpha),
            "ab.smallest_difference": repr(self.smallest_difference),
            # what a normalized point is on each env: the smallest difference and the suite's
            # scores are in those points, so a re-measured random score would move both
            "ab.normalization": ", ".join(
                f"{env}: random={score.random!r} reference={score.reference!r}"
                for env, score in self.scores.items()
            ),
        }


def _arms(arms) -> tuple[Arm, ...]:
    if not isinstance(arms, Mapping) or len(arms) < 2:
        raise ConfigError(
            f"hydra.sweeper.arms={arms!r} is not allowed: a mapping of at least two arms, "
            "name: overrides (e.g. {td3: algo=td3, sac: algo=sac})"
        )
    parser = OverridesParser.create()
    out = []
    for name, overrides in arms.items():
        if not _NAME.match(str(name)):
            raise ConfigError(f"arm name {name!r} is not allowed: letters, digits, '_', '.' or '-'")
        if isinstance(overrides, Mapping):
            out.append(_reference_arm(str(name), overrides))
            continue
        items = shlex.split(overrides) if isinstance(overrides, str) else list(overrides or [])
        try:
            parsed = parser.parse_overrides(items)
        except OverrideParseException as e:
            raise ConfigError(
                f"arm {name!r}: {overrides!r} is not a list of overrides: {str(e).splitlines()[0]}"
            ) from None
        for override in parsed:
            if override.is_sweep_override():
                raise ConfigError(
                    f"arm {name!r}: {override.input_line!r} sweeps several values: an arm is one "
                    "configuration (declare one arm per value)"
                )
            if override.get_key_element() in ("seed", "env", "job_key"):
                raise ConfigError(
                    f"arm {name!r}: {override.input_line!r} is not allowed: the study sets "
                    "seed, env and job_key for every job"
                )
        out.append(Arm(str(name), tuple(items)))
    return tuple(out)


def _reference_arm(name: str, declared: Mapping) -> Arm:
    """``{reference: PATH}`` (a results bundle), with ``arm: NAME`` where it holds a study's
    several arms."""
    unknown = set(declared) - {"reference", "arm"}
    path = declared.get("reference")
    if unknown or not isinstance(path, str) or not path:
        raise ConfigError(
            f"arm {name!r}: {dict(declared)!r} is not allowed: overrides, or a reference arm "
            "{reference: <bundle folder>, arm: <its arm in the bundle, optional>}"
        )
    of = declared.get("arm")
    return Arm(name, (), reference=path, of=None if of is None else str(of))


def _envs(envs) -> tuple[str, ...]:
    known = sorted(p.stem for p in (CONF_DIR / "env").glob("*.yaml"))
    if isinstance(envs, str):
        envs = [envs]
    if not envs:
        raise ConfigError(
            f"hydra.sweeper.envs={envs!r} is not allowed: a list of one or more of "
            f"{', '.join(known)}"
        )
    for env in envs:
        if env not in known:
            raise ConfigError(f"env={env!r} is not allowed: must be one of {', '.join(known)}")
    if len(set(envs)) < len(envs):
        raise ConfigError(f"hydra.sweeper.envs={list(envs)} names an env twice")
    return tuple(envs)


def env_scores(env: str) -> EnvScores:
    """``scores`` of ``conf/env/<env>.yaml`` (refused in one line if not measured yet)."""
    declared = yaml.safe_load((CONF_DIR / "env" / f"{env}.yaml").read_text()).get("scores") or {}
    random, reference = declared.get("random"), declared.get("reference")
    if random is None or reference is None or reference == random:
        raise ConfigError(
            f"env={env!r} has no scores.random and scores.reference in conf/env/{env}.yaml: "
            f"measure the random score with `python benchmarks/random_scores.py --envs {env}`"
        )
    return EnvScores(float(random), float(reference))
