"""Check a composed config before any work starts (and before an MLflow run exists).

Each rule names a dotted key, a predicate and, for the error message, what is allowed. Keys that
an algorithm does not have are skipped, so one table serves every algorithm.
"""

from __future__ import annotations

from numbers import Real

from omegaconf import DictConfig, OmegaConf

from walkers.agents.sb3_arguments import NotExpressible, sb3_arguments
from walkers.agents.sb3_twin import import_sb3
from walkers.errors import ConfigError
from walkers.metrics import METRIC_DIRECTIONS

OPTIMIZABLE_METRICS = tuple(METRIC_DIRECTIONS)  # every metric a sweep can optimize
DEVICES = ("auto", "cpu", "cuda")
IMPLEMENTATIONS = ("walkers", "sb3")


def _int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _number(v) -> bool:
    return isinstance(v, Real) and not isinstance(v, bool)


def positive_int(v) -> bool:
    return _int(v) and v > 0


def non_negative_int(v) -> bool:
    return _int(v) and v >= 0


def positive(v) -> bool:
    return _number(v) and v > 0


def non_negative(v) -> bool:
    return _number(v) and v >= 0


def unit_interval(v) -> bool:
    return _number(v) and 0 < v <= 1


def positive_or_null(v) -> bool:
    return v is None or positive(v)


def layer_sizes(v) -> bool:
    return isinstance(v, list) and len(v) > 0 and all(positive_int(x) for x in v)


RULES: list[tuple[str, callable, str]] = [
    ("seed", non_negative_int, "an integer >= 0"),
    ("total_steps", positive_int, "an integer > 0"),
    ("eval_every", positive_int, "an integer > 0"),
    ("eval_episodes", positive_int, "an integer > 0"),
    ("checkpoint_every", positive_int, "an integer > 0"),
    ("log_every", positive_int, "an integer > 0"),
    ("video_every", non_negative_int, "an integer >= 0 (0: no videos)"),
    ("divergence_patience", positive_int, "an integer > 0"),
    ("population", positive_int, "an integer > 0"),
    ("torch_threads", lambda v: v is None or positive_int(v), "null or an integer > 0"),
    ("device", lambda v: v in DEVICES, "one of " + ", ".join(DEVICES)),
    ("impl", lambda v: v in IMPLEMENTATIONS, "one of " + ", ".join(IMPLEMENTATIONS)),
    (
        "optimized_metric",
        lambda v: v in OPTIMIZABLE_METRICS,
        "one of " + ", ".join(OPTIMIZABLE_METRICS),
    ),
    ("algo.lr", positive, "a number > 0"),
    ("algo.actor_lr", positive_or_null, "null or a number > 0"),
    ("algo.critic_lr", positive_or_null, "null or a number > 0"),
    ("algo.batch_size", positive_int, "an integer > 0"),
    ("algo.buffer_size", positive_int, "an integer > 0"),
    ("algo.learning_starts", non_negative_int, "an integer >= 0"),
    ("algo.hidden_sizes", layer_sizes, "a non-empty list of integers > 0, e.g. [256,256]"),
    (
        "algo.critic_hidden_sizes",
        lambda v: v is None or layer_sizes(v),
        "null or a list of integers > 0",
    ),
    ("algo.gamma", unit_interval, "a number in (0, 1]"),
    ("algo.tau", unit_interval, "a number in (0, 1]"),
    ("algo.policy_delay", positive_int, "an integer > 0"),
    ("algo.policy_noise", non_negative, "a number >= 0"),
    ("algo.noise_clip", non_negative, "a number >= 0"),
    ("algo.exploration_noise", non_negative, "a number >= 0"),
    ("algo.alpha_init", positive, "a number > 0"),
    ("algo.alpha_lr", positive_or_null, "null or a number > 0"),
    ("algo.target_entropy", lambda v: v is None or _number(v), "null (-|A|) or a number"),
    ("algo.compile", lambda v: isinstance(v, bool), "true or false"),
    ("algo.context_length", positive_int, "an integer > 0"),
    ("algo.embed_dim", positive_int, "an integer > 0"),
    ("algo.n_layers", positive_int, "an integer > 0"),
    ("algo.n_heads", positive_int, "an integer > 0"),
    ("algo.dropout", lambda v: _number(v) and 0 <= v < 1, "a number in [0, 1)"),
    ("algo.weight_decay", non_negative, "a number >= 0"),
    ("algo.warmup_steps", non_negative_int, "an integer >= 0"),
    ("algo.grad_clip", positive, "a number > 0"),
    ("algo.return_scale", positive, "a number > 0"),
    ("algo.max_episode_steps", positive_int, "an integer > 0"),
    ("algo.max_grad_norm", positive_or_null, "null or a number > 0"),
    ("algo.n_steps", positive_int, "an integer > 0"),
    ("algo.n_epochs", positive_int, "an integer > 0"),
    ("algo.n_minibatches", positive_int, "an integer > 0"),
    ("algo.gae_lambda", lambda v: _number(v) and 0 <= v <= 1, "a number in [0, 1]"),
    ("algo.clip_coef", positive, "a number > 0"),
    ("algo.vf_coef", non_negative, "a number >= 0"),
    ("algo.ent_coef", non_negative, "a number >= 0"),
    ("algo.target_kl", positive_or_null, "null or a number > 0"),
    ("algo.activation", lambda v: v in ("tanh", "relu"), "tanh or relu"),
    ("algo.adam_eps", positive, "a number > 0"),
    ("algo.clip_obs", positive, "a number > 0"),
    ("algo.clip_reward", positive, "a number > 0"),
    (
        "algo.target_returns",
        lambda v: v is None or (isinstance(v, list) and len(v) > 0 and all(map(_number, v))),
        "null (the dataset's best return) or a non-empty list of numbers, e.g. [5000,2500]",
    ),
    ("env.max_episode_steps", lambda v: v is None or positive_int(v), "null or an integer > 0"),
    ("env.threshold", _number, "a number"),
    ("env.learning_starts", non_negative_int, "an integer >= 0"),
]

_MISSING = object()


def is_offline(cfg: DictConfig) -> bool:
    """Whether ``cfg.algo`` learns from a dataset (its agent class says ``offline = True``)."""
    from hydra.utils import get_class

    return bool(getattr(get_class(cfg.algo._target_), "offline", False))


def _check_population(cfg: DictConfig) -> None:
    from hydra.utils import get_class

    k = cfg.get("population", 1)
    if k == 1:
        return
    if not hasattr(get_class(cfg.algo._target_), "act_population"):
        raise ConfigError(
            f"population={k} is not allowed with algo={cfg.algo.name}: "
            "only td3, ddpg and sac train seed populations"
        )
    for key, unsupported in (("video_every", cfg.video_every), ("a sweep", cfg.trial.id)):
        if unsupported:
            raise ConfigError(
                f"population={k} is not allowed with {key}: run the population without it "
                "(videos: walkers.evaluate on a member's run)"
            )


def _check_implementation(cfg: DictConfig) -> None:
    """``impl=sb3``: an algorithm with an SB3 twin, settings SB3 can express, SB3 installed."""
    if cfg.get("impl", "walkers") != "sb3":
        return
    hyperparameters = OmegaConf.to_container(cfg.algo, resolve=True)
    try:
        sb3_arguments(cfg.algo.name, hyperparameters)
    except NotExpressible as e:
        raise ConfigError(str(e)) from None
    if cfg.population > 1:
        raise ConfigError(
            f"population={cfg.population} is not allowed with impl=sb3: SB3 trains one seed "
            "per process (use a multirun over seeds)"
        )
    import_sb3()


def _check_dataset(cfg: DictConfig) -> None:
    dataset = cfg.get("dataset")
    if is_offline(cfg) and not dataset:
        raise ConfigError(
            f"dataset={dataset!r} is not allowed: algo={cfg.algo.name} learns offline and needs "
            "dataset=<Minari dataset id> (record one with `python -m walkers.collect`)"
        )
    if not is_offline(cfg) and dataset:
        raise ConfigError(
            f"dataset={dataset!r} is not allowed with algo={cfg.algo.name}: only offline "
            "algorithms (dt) train on a dataset; online ones collect their own experience"
        )


def check(key: str, value, ok: bool, allowed: str) -> None:
    if not ok:
        raise ConfigError(f"{key}={value!r} is not allowed: must be {allowed}")


def validate(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` naming the first bad key, its value and what is allowed."""
    for key, predicate, allowed in RULES:
        value = OmegaConf.select(cfg, key, default=_MISSING)
        if value is _MISSING:
            continue
        if OmegaConf.is_config(value):
            value = OmegaConf.to_container(value, resolve=True)
        check(key, value, predicate(value), allowed)
    check(
        "eval_every",
        cfg.eval_every,
        cfg.eval_every <= cfg.total_steps,
        f"at most total_steps ({cfg.total_steps})",
    )
    _check_implementation(cfg)
    _check_dataset(cfg)
    _check_population(cfg)
    algo = cfg.algo
    if "batch_size" in algo and "buffer_size" in algo:
        check(
            "algo.batch_size",
            algo.batch_size,
            algo.batch_size <= algo.buffer_size,
            f"at most algo.buffer_size ({algo.buffer_size})",
        )
    if "n_minibatches" in algo and "n_steps" in algo:
        check(
            "algo.n_minibatches",
            algo.n_minibatches,
            algo.n_minibatches <= algo.n_steps,
            f"at most algo.n_steps ({algo.n_steps}): a minibatch holds at least one step",
        )
    if cfg.device == "cuda":
        import torch

        check(
            "device",
            "cuda",
            torch.cuda.is_available(),
            "auto or cpu on this machine (torch sees no CUDA device)",
        )
