"""The Hydra sweeper behind ``python -m walkers.train -m ab=NAME``: an A/B study in rounds.

Every round it reads what the study's jobs left in MLflow, answers each question with the
sequential test (:mod:`walkers.ab.rounds`), logs the interim answers to the study's run, and
launches the jobs the open questions need, through whatever launcher the command chose (basic,
joblib, Ray, submitit). A job is keyed by study, arm, env and seed (``job_key``), so:

- a rerun of the same command skips FINISHED jobs, and each job it launches again continues its
  earlier run (RUNNING with its process gone, KILLED, or FAILED with a checkpoint) from the last
  checkpoint (:mod:`walkers.training.command_plan`);
- no seed runs twice or counts twice: one FINISHED run per key.

On a GPU (``hydra.sweeper.seeds_as_population``: ``auto``, the default, where the jobs' device
is CUDA; ``true``; ``false``) a round's fresh seeds of an (arm, env) run as one population job
(``population=K``, for the algorithms that train populations): one process, one batched update
for all of them. Each member is still its own MLflow run under its own seed's job key (the job's
key holds ``{seed}``, which each member fills in), so reruns, resumes and the sequential rule
see the same runs a job per seed would make; and a member trains as the single run of its seed
(:mod:`walkers.seeding`). Seeds that ran before (a killed or failed attempt) are
continued one job each.

Bad input (an unknown arm config or env, a maximum below the minimum, alpha out of range, an arm
whose config changed since its runs started, a design other than the one the study started with)
is one ``error:`` line and exit 2 before anything runs.
"""

from __future__ import annotations

import logging
import sys
from typing import Any

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.plugins import Plugins
from hydra.core.utils import JobStatus
from hydra.errors import HydraException
from hydra.plugins.sweeper import Sweeper
from omegaconf import DictConfig, open_dict

from walkers.ab import ledger
from walkers.ab.outputs import write_results
from walkers.ab.reference_arms import reference_scores
from walkers.ab.rounds import standing
from walkers.ab.spec import StudySpec
from walkers.analysis.sequential import A_BETTER, B_BETTER, EQUAL, Design, equal_line
from walkers.cli import jobs_at_once, one_line_hydra_error
from walkers.errors import ConfigError
from walkers.tracking.client import connect, ending, flatten
from walkers.tracking.names import JOB_KEY_TAG
from walkers.training.provenance import DIVERGED_TAG, SEED_IN_KEY, shareable
from walkers.training.settings import validate
from walkers.tuning.study_runs import end_jobs_runs

log = logging.getLogger("walkers")

#: Command-line keys a study sets for each job itself.
STUDY_KEYS = ("seed", "env", "job_key", "trial.parent_run_id", "population")

#: hydra.sweeper.seeds_as_population's values
SEEDS_AS_POPULATION = ("auto", "true", "false")


class JobsFailed(RuntimeError):
    """Jobs of a round raised (on a cluster: a job's error comes back as its result)."""


class StudySweeper(Sweeper):
    """Hydra registers it as :class:`walkers.plugins.ABStudySweeper`, which builds it."""

    def __init__(self, **declared: Any) -> None:
        self.seeds_as_population = str(declared.pop("seeds_as_population", "auto")).lower()
        self.declared = declared

    def setup(self, *, hydra_context, task_function, config: DictConfig) -> None:
        self.config, self.hydra_context = config, hydra_context
        self.launcher = Plugins.instance().instantiate_launcher(
            config=config, hydra_context=hydra_context, task_function=task_function
        )
        self.job_idx = 0

    def sweep(self, arguments: list[str]) -> Any:
        try:
            spec = StudySpec.parse(**self.declared)
            design = spec.checked_design()  # before anything is created: a study that can decide
            base = self._base_overrides(arguments)
            self.results_rates: dict[tuple[str, str], float | None] = {}
            self.configs = configs = {
                (arm.name, env): self._job_config(base, spec, arm.name, env)
                for arm in spec.trained_arms
                for env in spec.envs
            }
            self.shared = {env: self._job_config(base, spec, None, env) for env in spec.envs}
            self.reference_scores = reference_scores(spec, self.shared)
            client = connect(self.config.tracking.uri)
            experiment = self.config.tracking.experiment
            ledger.check_arms_unchanged(ledger.job_runs(client, experiment, spec), spec, configs)
            self.populations = self._population_places(base, spec, configs)
            study = ledger.open_study_run(client, experiment, spec, self.config.work_dir)
        except ConfigError as e:
            print(f"error: {e}", file=sys.stderr)
            sys.exit(2)
        self._say_design(spec, design)
        try:
            with ending([study]):
                ledger.log_deciding_looks(study, design)
                final = self._rounds(client, experiment, spec, base, study)
        except KeyboardInterrupt:
            print(
                f"interrupted: study {spec.name!r} stopped (its runs KILLED, each continued from "
                "its last checkpoint by the same command)",
                file=sys.stderr,
            )
            log.info("open it: `make ui`, then %s", study.url)
            sys.exit(130)
        except JobsFailed as e:  # the study run is FAILED; its finished jobs are kept
            print(f"error: {e}", file=sys.stderr)
            sys.exit(1)
        print(ledger.standing_table(final))
        for line in verdicts(final):
            log.info("%s", line)
        loader = self.hydra_context.config_loader
        try:
            lines = write_results(loader, self.config, spec, client, self.shared)
        except KeyboardInterrupt:  # the study has ended; only its report and bundle are cut
            print(
                f"interrupted: study {spec.name!r} ended {study.status}; its report and bundle "
                "were not written (the same command writes them)",
                file=sys.stderr,
            )
            sys.exit(130)
        for line in lines:
            log.info("%s", line)
        log.info("study %r: MLflow run %s ended %s", spec.name, study.run_id, study.status)
        log.info("open it: `make ui`, then %s", study.url)
        return final

    # --- the rounds ---------------------------------------------------------------------------
    def _rounds(self, client, experiment: str, spec: StudySpec, base: list[str], study):
        while True:
            runs = ledger.job_runs(client, experiment, spec)
            scores = ledger.finished_scores(runs, spec) | self.reference_scores
            now = standing(spec, scores)
            hours = ledger.cpu_hours_by_arm(runs, spec)
            ledger.log_standing(study, now, sum(len(v) for v in scores.values()), hours)
            jobs = now.missing(scores)
            if not jobs:
                log.info("%s", ledger.cpu_hours_line(hours))
                return now
            _refuse_diverged(runs, {spec.job_key(*job) for job in jobs})
            # the most work left first (fresh jobs, then resumed ones by the steps they lack): a
            # round ends with its last job, and a long one started last would run alone
            logged = ledger.steps_logged(runs)
            jobs.sort(key=lambda job: logged.get(spec.job_key(*job), 0))
            started = {run.data.tags.get(JOB_KEY_TAG) for run in runs}
            launches = self._launches(spec, jobs, started)
            log.info(
                "study %r, look %d: %d of %d questions open; launching %d jobs%s",
                spec.name,
                now.look + 2,
                sum(not q.answer.settled for q in now.questions),
                len(now.questions),
                len(launches),
                f" ({len(jobs)} seeds)" if len(launches) < len(jobs) else "",
            )
            steps_left = [
                sum(
                    max(0, int(self.configs[(arm, env)]["total_steps"]) - logged.get(key, 0))
                    for key in (spec.job_key(arm, env, seed) for seed in seeds)
                )
                for arm, env, seeds in launches
            ]
            cost = ledger.expected_cost(
                launches,
                steps_left,
                *self._hours_per_step(runs, spec),
            )
            log.info("study %r, look %d: %s", spec.name, now.look + 2, cost)
            self._launch(client, experiment, spec, base, launches, study.run_id)

    def _hours_per_step(self, runs: list, spec: StudySpec) -> tuple[dict, int | None, set]:
        """What an env step of each (arm, env) costs: as its own runs measured it, else as the
        committed results' runs of its algorithm on its env did (looked up once); the jobs run
        at once; the (arm, env)s whose rate is the results'. :func:`ledger.expected_cost`'s
        arguments."""
        rates = ledger.hours_per_step(runs, spec)
        for (arm, env), config in self.configs.items():
            if (arm, env) not in rates and (arm, env) not in self.results_rates:
                algo, env_id = config.get("algo.name"), config.get("env.id")
                self.results_rates[(arm, env)] = ledger.hours_per_step_in_results(algo, env_id)
        found = {
            key: rate
            for key, rate in self.results_rates.items()
            if rate is not None and key not in rates
        }
        return found | rates, jobs_at_once(self.config.hydra.launcher), set(found)

    def _launches(self, spec, jobs, started: set) -> list[tuple[str, str, list[int]]]:
        """The round's jobs as launches ``(arm, env, seeds)``: where an (arm, env) runs its seeds
        as a population, each run of its consecutive fresh seeds (no run yet) is one launch;
        every other seed is a launch of its own."""
        launches: list[tuple[str, str, list[int]]] = []
        for arm, env, seed in jobs:
            fresh = spec.job_key(arm, env, seed) not in started
            last = launches[-1] if launches else None
            if (
                fresh
                and (arm, env) in self.populations
                and last is not None
                and last[:2] == (arm, env)
                and last[2][-1] == seed - 1
                and spec.job_key(arm, env, last[2][0]) not in started
            ):
                last[2].append(seed)
            else:
                launches.append((arm, env, [seed]))
        return launches

    def _launch(self, client, experiment, spec, base, launches, parent_run_id: str) -> None:
        keys = [[spec.job_key(arm, env, seed) for seed in seeds] for arm, env, seeds in launches]
        batch = [
            base
            + list(spec.arm(arm).overrides)
            + self._job_overrides(spec, arm, env, seeds)
            + [f"trial.parent_run_id={parent_run_id}"]
            for arm, env, seeds in launches
        ]
        every_key = [key for group in keys for key in group]
        try:
            returns = self.launcher.launch(batch, initial_job_idx=self.job_idx)
        except SystemExit as e:  # a job in this process (basic launcher) exits: 130 interrupted
            interrupted = e.code == 130
            end_jobs_runs(client, experiment, every_key, KeyboardInterrupt() if interrupted else e)
            if interrupted:
                raise KeyboardInterrupt from e
            raise
        except BaseException as e:
            end_jobs_runs(client, experiment, every_key, e)
            raise
        self.job_idx += len(returns)
        failed = [
            (group[0], r)
            for group, r in zip(keys, returns, strict=True)
            if r.status == JobStatus.FAILED
        ]
        if failed:
            key, ret = failed[0]
            raise JobsFailed(
                f"{len(failed)} job(s) of study {spec.name!r} failed, first {key}: "
                f"{type(ret._return_value).__name__}: {ret._return_value}; fix it and run the "
                "same command again (finished jobs are kept)"
            )

    @staticmethod
    def _job_overrides(spec, arm: str, env: str, seeds: list[int]) -> list[str]:
        """What a launch sets: its env and first seed, and its job key and run name (one seed),
        or ``population=K`` with ``{seed}`` in both, for each member to fill in."""
        one = len(seeds) == 1
        seed = str(seeds[0]) if one else SEED_IN_KEY
        key, name = spec.job_key(arm, env, seed), f"ab-{spec.name}-{arm}-{env}-s{seed}"
        q = "" if one else "'"  # Hydra's override grammar reads an unquoted {...} as a dict
        population = [] if one else [f"population={len(seeds)}"]
        return [
            f"env={env}",
            f"seed={seeds[0]}",
            *population,
            f"job_key={q}{key}{q}",
            f"tracking.run_name={q}{name}{q}",
        ]

    def _population_places(self, base, spec: StudySpec, configs) -> set[tuple[str, str]]:
        """The (arm, env)s whose fresh seeds run as one population job: by
        ``seeds_as_population`` (``auto``: where the jobs' device is CUDA), where the arm's
        algorithm trains populations (an arm that cannot runs a job per seed, and says so)."""
        if self.seeds_as_population not in SEEDS_AS_POPULATION:
            raise ConfigError(
                f"hydra.sweeper.seeds_as_population={self.seeds_as_population!r} is not allowed: "
                f"one of {', '.join(SEEDS_AS_POPULATION)}"
            )
        if self.seeds_as_population == "false":
            return set()
        places = set()
        for arm, env in configs:
            device = configs[(arm, env)].get("device", "cpu")
            on_gpu = device == "cuda" or (device == "auto" and _cuda_available())
            if self.seeds_as_population == "auto" and not on_gpu:
                continue
            try:
                self._job_config([*base, "population=2"], spec, arm, env)
            except ConfigError as e:
                log.info("study %r: arm %r runs a job per seed on %s (%s)", spec.name, arm, env, e)
                continue
            places.add((arm, env))
        if places:
            log.info(
                "study %r: each round's new seeds run as one population job for %s",
                spec.name,
                ", ".join(f"{arm} on {env}" for arm, env in sorted(places)),
            )
        return places

    # --- checks before anything runs ----------------------------------------------------------
    def _base_overrides(self, arguments: list[str]) -> list[str]:
        """The command line's overrides, which every job gets (sweeps and study keys refused)."""
        for override in OverridesParser.create().parse_overrides(arguments):
            key = override.get_key_element()
            if override.is_sweep_override():
                raise ConfigError(
                    f"{override.input_line}: a study runs its own seeds and arms; sweep nothing "
                    "on its command line (declare arms in the study file)"
                )
            if key in STUDY_KEYS:
                raise ConfigError(
                    f"{override.input_line}: the study sets {key} for each job (seeds: "
                    "hydra.sweeper.seeds, envs: hydra.sweeper.envs, populations: "
                    "hydra.sweeper.seeds_as_population)"
                )
        return list(arguments)

    def _job_config(self, base: list[str], spec: StudySpec, arm: str | None, env: str) -> dict:
        """The arm's resolved config on ``env`` (seed 0) as params, checked like a run's;
        ``arm=None``: what every job shares there (the command line, no arm's overrides)."""
        arm_overrides = list(spec.arm(arm).overrides) if arm is not None else []
        overrides = base + arm_overrides + [f"env={env}"]
        where = f"arm {arm!r}" if arm is not None else "the study's command line"
        try:
            cfg = self.hydra_context.config_loader.load_sweep_config(self.config, overrides)
        except HydraException as e:
            raise ConfigError(f"{where}: {one_line_hydra_error(e, overrides)}") from None
        with open_dict(cfg):
            del cfg["hydra"]
        try:
            validate(cfg)
        except ConfigError as e:
            raise ConfigError(f"{where} on {env}: {e}") from None
        return flatten(shareable(cfg))

    def _say_design(self, spec: StudySpec, design: Design) -> None:
        log.info(
            "study %r: %d arms x %d envs, %d questions (alpha %.3g, Bonferroni: %.3g each); "
            "looks at %s seeds per arm; smallest difference %.3g normalized points",
            spec.name,
            len(spec.arms),
            len(spec.envs),
            design.questions,
            spec.alpha,
            design.alpha_per_question,
            ", ".join(map(str, design.looks)),
            spec.smallest_difference,
        )
        deciding = design.deciding_looks()
        if len(deciding) < len(design.looks):  # one line that stands out among the jobs' logs
            idle = [n for k, n in enumerate(design.looks) if k not in deciding]
            print(
                f"warning: study {spec.name!r}: at {_seeds(idle)} seeds per arm no look can "
                f"decide anything whatever the returns (only 'continue'); the looks at "
                f"{_seeds([design.looks[k] for k in deciding])} can (`python -m walkers.plan "
                f"study=...` shows each look)",
                file=sys.stderr,
            )
        log.info("study %r: %s", spec.name, equal_line(design))


def _refuse_diverged(runs: list, keys: set[str]) -> None:
    """A seed whose run diverged can be neither counted (it has no final score) nor trained
    again: on a CPU it diverges again at the same step, and an attempt that did not (a GPU's
    nondeterminism) would leave the arm's failures out of its samples."""
    for run in ledger.diverged(runs, keys):
        raise JobsFailed(
            f"job {run.data.tags[JOB_KEY_TAG]} diverged at step "
            f"{run.data.tags[DIVERGED_TAG]} (run {run.info.run_id}): a study can neither count "
            "the seed nor train it again (a new attempt would diverge again, or leave the arm's "
            "failures out of its samples); change the arm (a lower learning rate, say) and run it "
            "as a new study"
        )


def _cuda_available() -> bool:
    import torch

    return torch.cuda.is_available()


def _seeds(counts: list[int]) -> str:
    return ", ".join(map(str, counts))


def verdicts(final) -> list[str]:
    """One sentence per question, in plain words."""
    out = []
    for q in final.questions:
        r, where = q.answer, q.env or "the suite (aggregate of normalized scores)"
        if r.decision == A_BETTER:
            text = f"{q.a} is better than {q.b} on {where}"
        elif r.decision == B_BETTER:
            text = f"{q.b} is better than {q.a} on {where}"
        elif r.decision == EQUAL:
            text = f"{q.a} and {q.b} are equal within the smallest difference on {where}"
        else:
            text = f"{q.a} vs {q.b} on {where}: not settled at the maximum seeds"
            if r.power == r.power:
                text += f" (power for the smallest difference: at least {r.power:.2f})"
        out.append(f"{text} ({r.seeds} seeds per arm, p = {r.p_value:.4g})")
    return out
