"""Each algorithm's hyperparameters, declared once, and how a hyperparameter is declared: once,
with its default, type, allowed values and doc.

Each algorithm's hyperparameters are a dataclass (below, in :data:`SCHEMAS`) whose fields are made
by :func:`hp`. Everything else is derived from that one declaration:

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

A class's docstring heads its menu ``conf/algo/<name>.yaml``; a field's doc comments its value
there. ``make menus`` (:mod:`walkers.agents.declarations.menus`) rewrites the menus after a change
here.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from numbers import Real
from typing import Any, ClassVar

from walkers.errors import did_you_mean


# --- how a hyperparameter is declared --------------------------------------------------------
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


# --- each algorithm's declaration -------------------------------------------------------------
#: What the menus of names offer, by name: what each name builds lives beside the torch code
#: (``CRITIC_ARCHITECTURES``, ``NOISE_TYPES``, ``ACTIVATIONS`` in :mod:`walkers.agents.common`,
#: ``PRECISIONS`` in :mod:`walkers.agents.base`; tests/agents/test_hyperparameters.py holds them
#: equal), so that
#: checking a config, comparing runs or planning a study imports no torch.
CRITIC_ARCHITECTURE_NAMES = ("mlp", "layernorm_branch")
NOISE_TYPE_NAMES = ("gaussian", "ou")
ACTIVATION_NAMES = ("tanh", "relu")
PRECISION_NAMES = ("fp32", "bf16")

COMPILE_DOC = (
    "torch.compile: on CPU the whole update of TD3, DDPG and SAC (1.2-1.3x,\n"
    "docs/speed.md), the losses of the others (no gain); on CUDA the losses\n"
    "with CUDA graphs. Floats rounded otherwise than eager: an arm of its own"
)
PRECISION_DOC = (
    "fp32 (the reference) | bf16: the update under bfloat16 autocast (matmuls in\n"
    "bfloat16; weights, optimizer and losses in fp32), acting in fp32. Faster on a\n"
    "CPU with AMX or AVX-512 BF16 (docs/speed.md); other rounding: an arm of its own"
)
CAPTURE_DOC = (
    "the whole update (sampling, losses, backward, optimizer steps, guard,\n"
    "targets) as CUDA graphs, replayed: auto = on CUDA unless compile is on;\n"
    "the same update as the eager one (H200: TD3's update 0.46 ms against 6.8)"
)
#: ``capture``: ``auto`` turns it on where it runs (CUDA) and compile is off.
CAPTURE = Allowed(lambda v: isinstance(v, bool) or v == "auto", "auto, true or false")


def warmup(default: int, source: str = ""):
    """``learning_starts``: the uniform random warm-up of a replay-based algorithm."""
    return hp(
        default,
        NON_NEGATIVE_INT,
        f"uniform random actions (no updates) for this many env steps{source}; short envs set "
        "env.learning_starts",
        env_key="learning_starts",
    )


#: A learning rate of its own, or null to share ``lr``.
LR_OR_SHARED = or_null(POSITIVE, "lr")


@dataclass
class Replay(Hyperparameters):
    """What the replay-based actor-critics (TD3, DDPG, SAC, CrossQ) share."""

    AT_MOST = {"batch_size": ("buffer_size", "")}
    TINY = {"hidden_sizes": [32, 32], "batch_size": 32, "learning_starts": 100}

    lr: float = hp(3.0e-4, POSITIVE, "Adam learning rate, actor and critics")
    batch_size: int = hp(256, POSITIVE_INT, "transitions per gradient step")
    learning_starts: int = warmup(25_000)
    hidden_sizes: list[int] = hp([256, 256], LAYERS, "hidden layers of actor and critics")
    gamma: float = hp(0.99, DISCOUNT, "discount")
    buffer_size: int = hp(1_000_000, POSITIVE_INT, "replay buffer capacity (transitions)")
    compile: bool = hp(False, BOOL, COMPILE_DOC)
    capture: bool | str = hp("auto", CAPTURE, CAPTURE_DOC)


@dataclass
class OffPolicy(Replay):
    """TD3, DDPG and SAC: replay and target networks."""

    tau: float = hp(0.005, DISCOUNT, "target networks: theta' <- tau * theta + (1 - tau) * theta'")
    precision: str = hp("fp32", one_of(*PRECISION_NAMES), PRECISION_DOC)


@dataclass
class TD3Ideas(Hyperparameters):
    """TD3's target policy smoothing and delayed policy updates (TD3 and TD3+BC)."""

    policy_noise: float = hp(
        0.2,
        NON_NEGATIVE,
        "target policy smoothing noise std (fraction of the action range half-width)",
    )
    noise_clip: float = hp(0.5, NON_NEGATIVE, "clip of that noise (same units)")
    policy_delay: int = hp(2, POSITIVE_INT, "critic updates per actor/target update")


@dataclass
class TD3Hyperparameters(TD3Ideas, OffPolicy):
    """TD3 (Fujimoto et al. 2018, "Addressing Function Approximation Error in Actor-Critic
    Methods"). Defaults are the reference implementation's."""

    AGENT = "walkers.agents.td3.TD3"
    NAME = "td3"
    exploration_noise: float = hp(
        0.1,
        NON_NEGATIVE,
        "Gaussian exploration noise std (fraction of the action range half-width)",
    )


@dataclass
class DDPGHyperparameters(OffPolicy):
    """DDPG (Lillicrap et al. 2016) as "our DDPG" of the TD3 paper: TD3's networks and update
    with one critic, no target policy smoothing and no policy delay."""

    AGENT = "walkers.agents.ddpg.DDPG"
    NAME = "ddpg"
    lr: float = hp(3.0e-4, POSITIVE, "Adam learning rate, actor and critic")
    hidden_sizes: list[int] = hp(
        [256, 256],
        LAYERS,
        "hidden layers of the actor (and of the critic when critic_architecture=mlp)",
    )
    actor_lr: float | None = hp(
        None,
        LR_OR_SHARED,
        "set to give the actor its own learning rate (the tutorial's lr_actor)",
    )
    critic_lr: float | None = hp(
        None,
        LR_OR_SHARED,
        "set to give the critic its own learning rate (the tutorial's lr_critic)",
    )
    critic_architecture: str = hp(
        "mlp",
        one_of(*CRITIC_ARCHITECTURE_NAMES),
        "mlp: TD3's critic (the tutorial's \"same structure\");\n"
        "layernorm_branch: the tutorial's critic (state layers Linear+LayerNorm+ReLU,\n"
        "action merged at the last hidden layer)",
    )
    critic_hidden_sizes: list[int] | None = hp(
        None, or_null(LAYERS, "hidden_sizes"), "critic layers; null = hidden_sizes"
    )
    exploration_noise: float = hp(
        0.1, NON_NEGATIVE, "exploration noise std (fraction of the action range half-width)"
    )
    noise_type: str = hp(
        "gaussian",
        one_of(*NOISE_TYPE_NAMES),
        "gaussian | ou (Ornstein-Uhlenbeck, theta 0.15, reset every episode)",
    )


@dataclass
class SACHyperparameters(OffPolicy):
    """SAC (Haarnoja et al. 2018, "Soft Actor-Critic Algorithms and Applications": the "v2" with a
    learned temperature, twin critics and no value network). Defaults are the paper's
    hyperparameter table (its appendix), except the warm-up (learning_starts): TD3's, so SAC and
    TD3 arms of a study start alike (RL-Zoo and Spinning Up use 10k on MuJoCo, CleanRL 5k).
    Fixed by the algorithm: two critics (clipped double-Q), actor and temperature updated every
    gradient step, one gradient step per env step, log sigma clamped to [-20, 2], the policy's own
    sample explores (no added noise), deterministic evaluation with tanh(mean)."""

    AGENT = "walkers.agents.sac.SAC"
    NAME = "sac"
    lr: float = hp(3.0e-4, POSITIVE, "Adam learning rate: actor, critics and temperature")
    tau: float = hp(
        0.005,
        DISCOUNT,
        "target critics: theta' <- tau * theta + (1 - tau) * theta' (every gradient step)",
    )
    alpha_init: float = hp(
        1.0,
        POSITIVE,
        "initial entropy temperature alpha (learned from there; SB3, CleanRL: 1.0)",
    )
    alpha_lr: float | None = hp(
        None,
        LR_OR_SHARED,
        "the temperature's learning rate; null = lr (as the paper and SB3)",
    )
    target_entropy: float | None = hp(
        None,
        or_null(NUMBER, "-|A|"),
        "the entropy alpha steers towards; null = -|A| (minus the action dimension)",
    )


BETAS = Allowed(
    lambda v: isinstance(v, list) and len(v) == 2 and all(PROBABILITY.ok(b) and b < 1 for b in v),
    "two numbers in [0, 1), e.g. [0.5,0.999]",
)


@dataclass
class CrossQHyperparameters(Replay):
    """CrossQ (Bhatt, Palenicek et al., ICLR 2024, "CrossQ: Batch Normalization in Deep
    Reinforcement Learning for Greater Sample Efficiency and Simplicity"): SAC without target
    networks, Batch Renormalization in actor and critics, one joint critic pass over (s, a) and
    (s', a'). Defaults are the paper's (critics 2048 wide, lr 1e-3, Adam betas 0.5/0.999, actor
    every 3rd update) with sb3-contrib's renormalization settings. On a CPU the wide critics
    cost: critic_hidden_sizes=[256,256] runs at about SAC's speed (README, Speed).
    Fixed by the algorithm: two critics, the temperature's step with the actor's (before it),
    no target networks, deterministic evaluation with tanh(mean) in running statistics."""

    AGENT = "walkers.agents.crossq.CrossQ"
    NAME = "crossq"
    #: the renormalization past its warm-up within a tiny run's updates
    TINY = {**Replay.TINY, "critic_hidden_sizes": [32, 32], "renorm_warmup_steps": 100}
    lr: float = hp(1.0e-3, POSITIVE, "Adam learning rate: actor, critics and temperature")
    learning_starts: int = warmup(5_000, " (the paper's code: 5000)")
    hidden_sizes: list[int] = hp([256, 256], LAYERS, "hidden layers of the actor")
    critic_hidden_sizes: list[int] = hp(
        [2048, 2048],
        LAYERS,
        "hidden layers of each critic (the paper's 2048; sb3-contrib's default 1024;\n"
        "on a CPU [256,256] keeps SAC's speed: README, Speed)",
    )
    adam_betas: list[float] = hp(
        [0.5, 0.999], BETAS, "Adam (beta1, beta2) of actor and critics (the paper's beta1 0.5)"
    )
    policy_delay: int = hp(3, POSITIVE_INT, "critic updates per actor and temperature update")
    renorm_momentum: float = hp(
        0.01,
        PROBABILITY,
        "Batch Renormalization: running statistics move this fraction towards each batch's",
    )
    renorm_warmup_steps: int = hp(
        100_000,
        NON_NEGATIVE_INT,
        "training passes of plain batch statistics before the renormalization's correction",
    )
    alpha_init: float = hp(1.0, POSITIVE, "initial entropy temperature alpha (learned from there)")
    alpha_lr: float | None = hp(
        None, LR_OR_SHARED, "the temperature's learning rate; null = lr (as sb3-contrib)"
    )
    target_entropy: float | None = hp(
        None,
        or_null(NUMBER, "-|A|"),
        "the entropy alpha steers towards; null = -|A| (minus the action dimension)",
    )


@dataclass
class PPOHyperparameters(Hyperparameters):
    """PPO (Schulman et al. 2017, "Proximal Policy Optimization Algorithms"), continuous control.
    Defaults are the reference values for MuJoCo (the paper's Table 3, OpenAI baselines ppo2's
    mujoco defaults, CleanRL ppo_continuous_action.py); see walkers/agents/ppo.py."""

    AGENT = "walkers.agents.ppo.PPO"
    NAME = "ppo"
    TINY = {"n_steps": 128, "n_minibatches": 4, "n_epochs": 2}  # updates every 128 steps
    AT_MOST = {"n_minibatches": ("n_steps", ": a minibatch holds at least one step")}
    DIVIDES = {"num_envs": ("n_steps", ": each env collects n_steps / num_envs of a rollout")}
    lr: float = hp(3.0e-4, POSITIVE, "Adam learning rate (policy and value share one optimizer)")
    anneal_lr: bool = hp(
        True, BOOL, "anneal the learning rate linearly to 0 over the run's total_steps"
    )
    total_steps: int | None = hp(
        None,
        or_null(POSITIVE_INT, "no annealing horizon"),
        "the run's budget, for the annealing (follows total_steps on resume)",
        follows="total_steps",
    )
    adam_eps: float = hp(
        1.0e-5, POSITIVE, "Adam epsilon (the reference's; torch's default is 1e-8)"
    )
    n_steps: int = hp(2048, POSITIVE_INT, "env steps per rollout (one update per rollout)")
    num_envs: int = hp(
        1,
        POSITIVE_INT,
        "envs stepped together, each n_steps / num_envs steps of every rollout,\n"
        "acting as one batch (1: the reference's single env; see make bench-envs)",
    )
    n_epochs: int = hp(10, POSITIVE_INT, "passes over each rollout")
    n_minibatches: int = hp(
        32,
        POSITIVE_INT,
        "shuffled minibatches per pass: 2048 / 32 = 64 steps each (SB3's batch_size)",
    )
    gamma: float = hp(0.99, DISCOUNT, "discount")
    gae_lambda: float = hp(
        0.95,
        PROBABILITY,
        "GAE(lambda) bias-variance trade-off (1: Monte-Carlo, 0: one-step TD)",
    )
    clip_coef: float = hp(
        0.2,
        POSITIVE,
        "epsilon of the clipped surrogate: the ratio pi/pi_old is clipped to [1-eps, 1+eps]",
    )
    clip_value_loss: bool = hp(
        False,
        BOOL,
        "true: clip the value update around the old values by clip_coef, as ppo2 and CleanRL do;\n"
        "off as in SB3: Andrychowicz et al. 2021 found it hurts; ab=ppo_value_clip scored it lower",
    )
    vf_coef: float = hp(
        0.5, NON_NEGATIVE, "weight of the value loss 1/2 (V - R)^2 in the total loss"
    )
    ent_coef: float = hp(
        0.0, NON_NEGATIVE, "weight of the entropy bonus (0 for MuJoCo in the reference)"
    )
    max_grad_norm: float | None = hp(
        0.5,
        or_null(POSITIVE, "no clip"),
        "global gradient-norm clip over both networks; null disables",
    )
    target_kl: float | None = hp(
        None,
        or_null(POSITIVE, "never"),
        "stop a rollout's epochs early when the mean approx KL of an epoch exceeds this; "
        "null: never",
    )
    normalize_advantages: bool = hp(True, BOOL, "standardize advantages within each minibatch")
    hidden_sizes: list[int] = hp(
        [64, 64], LAYERS, "hidden layers of the policy mean and of the (separate) value network"
    )
    activation: str = hp("tanh", one_of(*ACTIVATION_NAMES), "tanh (the reference) | relu")
    log_std_init: float = hp(
        0.0,
        NUMBER,
        "initial log-std of the Gaussian policy (std 1), state-independent and learned",
    )
    normalize_obs: bool = hp(
        True,
        BOOL,
        "observations normalized by running mean/std inside the agent (reported returns "
        "stay the env's)",
    )
    clip_obs: float = hp(10.0, POSITIVE, "normalized observations clipped to [-clip_obs, clip_obs]")
    normalize_reward: bool = hp(
        True,
        BOOL,
        "rewards divided by the running std of the discounted return (learning signal only)",
    )
    clip_reward: float = hp(10.0, POSITIVE, "scaled rewards clipped to [-clip_reward, clip_reward]")


@dataclass
class ReinforceHyperparameters(Hyperparameters):
    """REINFORCE (Williams 1992): Monte-Carlo policy gradient with a Gaussian policy; no critic.
    The stabilizers the original study needed are on by default (walkers/agents/reinforce.py)."""

    AGENT = "walkers.agents.reinforce.Reinforce"
    NAME = "reinforce"
    TINY = {"episodes_per_update": 1}
    lr: float = hp(1.0e-3, POSITIVE, "Adam learning rate of the policy")
    hidden_sizes: list[int] = hp(
        [64, 64], LAYERS, "hidden layers of the policy mean (and of the baseline)"
    )
    gamma: float = hp(0.99, DISCOUNT, "discount of the returns-to-go")
    episodes_per_update: int = hp(10, POSITIVE_INT, "complete episodes per gradient step")
    normalize_returns: bool = hp(True, BOOL, "standardize returns (advantages) over each batch")
    max_grad_norm: float | None = hp(
        0.5, or_null(POSITIVE, "no clip"), "global gradient-norm clip; null disables"
    )
    log_std_init: float = hp(-0.5, NUMBER, "initial log standard deviation of the Gaussian policy")
    log_std_min: float | None = hp(
        -5.0,
        or_null(NUMBER, "no bound"),
        "log-std clamp (numerical stability); null disables the lower bound",
    )
    log_std_max: float | None = hp(1.0, or_null(NUMBER, "no bound"), "upper bound; null disables")
    baseline: bool = hp(
        False,
        BOOL,
        "learn a state-value baseline V(s) (advantage G - V); off = the study's plain REINFORCE",
    )
    baseline_lr: float = hp(1.0e-3, POSITIVE, "Adam learning rate of the baseline")
    entropy_coef: float = hp(0.0, NON_NEGATIVE, "entropy bonus weight")


@dataclass
class DecisionTransformerHyperparameters(Hyperparameters):
    """Decision Transformer (Chen et al. 2021, "Decision Transformer: Reinforcement Learning via
    Sequence Modeling"): trained offline on a Minari dataset, e.g. one recorded by
    `python -m walkers.collect`.
      python -m walkers.train algo=dt env=walker2d dataset=walkers/walker2d/td3-expert
    Defaults are the reference implementation's. This file sets the x-axis keys too: for an offline
    algorithm total_steps, eval_every, checkpoint_every and log_every count gradient steps."""

    AGENT = "walkers.agents.dt.DecisionTransformer"
    NAME = "dt"
    TINY = {"embed_dim": 32, "n_layers": 1, "context_length": 5, "batch_size": 8}
    RUN_SETTINGS = {
        "total_steps": (100_000, "gradient steps"),
        "eval_every": (
            10_000,
            "gradient steps between evaluations (eval_episodes per target return)",
        ),
        "checkpoint_every": (10_000, "gradient steps between checkpoints"),
    }
    context_length: int = hp(
        20, POSITIVE_INT, "K: steps of (return-to-go, state, action) the transformer sees"
    )
    embed_dim: int = hp(128, POSITIVE_INT, "token embedding width")
    n_layers: int = hp(3, POSITIVE_INT, "transformer blocks")
    n_heads: int = hp(1, POSITIVE_INT, "attention heads per block")
    dropout: float = hp(0.1, DROPOUT, "on embeddings, attention and MLPs")
    lr: float = hp(1.0e-4, POSITIVE, "AdamW learning rate (after warm-up)")
    weight_decay: float = hp(1.0e-4, NON_NEGATIVE, "AdamW weight decay")
    warmup_steps: int = hp(
        10_000, NON_NEGATIVE_INT, "gradient steps of linear learning-rate warm-up"
    )
    batch_size: int = hp(64, POSITIVE_INT, "sequences per gradient step")
    grad_clip: float = hp(0.25, POSITIVE, "gradient-norm clip")
    precision: str = hp(
        "fp32",
        one_of(*PRECISION_NAMES),
        "fp32 (the reference) | bf16: the transformer under bfloat16 autocast, weights and "
        "optimizer in fp32 (1.35-1.57x faster a step on a CPU with AVX-512 BF16; other rounding)",
    )
    max_episode_steps: int = hp(
        1000, POSITIVE_INT, "timestep embeddings", env_key="max_episode_steps"
    )
    return_scale: float = hp(
        1000,
        POSITIVE,
        "returns-to-go are divided by this (per env: conf/env/)",
        env_key="return_scale",
    )
    target_returns: list[float] | None = hp(
        None,
        or_null(NUMBERS, "the dataset's best return"),
        "returns to condition evaluations on; the first is the headline; null: the dataset's best",
        env_key="target_returns",
    )


@dataclass
class TD3BCHyperparameters(TD3Ideas):
    """TD3+BC (Fujimoto & Gu 2021, "A Minimalist Approach to Offline Reinforcement Learning"):
    TD3 trained offline on a Minari dataset (e.g. one recorded by `python -m walkers.collect`),
    its actor loss -lambda Q(s, pi(s)) + (pi(s) - a)^2, lambda = alpha / mean |Q|.
      python -m walkers.train algo=td3bc env=walker2d dataset=walkers/walker2d/td3-expert
    Defaults are the reference implementation's. This file sets the x-axis keys too: for an offline
    algorithm total_steps, eval_every, checkpoint_every and log_every count gradient steps."""

    AGENT = "walkers.agents.td3bc.TD3BC"
    NAME = "td3bc"
    TINY = {"hidden_sizes": [32, 32], "batch_size": 16}
    RUN_SETTINGS = {
        "total_steps": (1_000_000, "gradient steps"),
        "eval_every": (5_000, "gradient steps between evaluations"),
        "checkpoint_every": (50_000, "gradient steps between checkpoints"),
    }
    lr: float = hp(3.0e-4, POSITIVE, "Adam learning rate, actor and critics")
    batch_size: int = hp(256, POSITIVE_INT, "dataset transitions per gradient step")
    hidden_sizes: list[int] = hp([256, 256], LAYERS, "hidden layers of actor and critics")
    gamma: float = hp(0.99, DISCOUNT, "discount")
    tau: float = hp(0.005, DISCOUNT, "target networks: theta' <- tau * theta + (1 - tau) * theta'")
    alpha: float = hp(
        2.5,
        POSITIVE,
        "weight of the Q term against behaviour cloning: lambda = alpha / mean |Q(s, pi(s))|",
    )
    normalize_states: bool = hp(
        True,
        BOOL,
        "normalize states with the dataset's mean and std (+ 1e-3), in training and acting",
    )
    compile: bool = hp(False, BOOL, COMPILE_DOC)
    capture: bool | str = hp("auto", CAPTURE, CAPTURE_DOC)
    precision: str = hp("fp32", one_of(*PRECISION_NAMES), PRECISION_DOC)


@dataclass
class TD7Hyperparameters(TD3Ideas, Replay):
    """TD7 (Fujimoto et al. 2023, "For SALE: State-Action Representation Learning for Deep
    Reinforcement Learning"): TD3 with SALE embeddings, LAP prioritised replay, hard target
    updates and value clipping; without the paper's policy checkpoints. Defaults are the
    authors' code's (github.com/sfujim/TD7)."""

    AGENT = "walkers.agents.td7.TD7"
    NAME = "td7"
    TINY = Replay.TINY | {"zs_dim": 16, "encoder_hidden_sizes": [32, 32], "target_update_rate": 20}
    lr: float = hp(3.0e-4, POSITIVE, "Adam learning rate: actor, critics and encoder")
    policy_delay: int = hp(2, POSITIVE_INT, "critic updates per actor update")
    exploration_noise: float = hp(
        0.1,
        NON_NEGATIVE,
        "Gaussian exploration noise std (fraction of the action range half-width)",
    )
    target_update_rate: int = hp(
        250,
        POSITIVE_INT,
        "updates between hard copies of the targets (actor, critics, both fixed\n"
        "encoders), LAP's largest priority and the value clipping's bounds",
    )
    lap_alpha: float = hp(0.4, NON_NEGATIVE, "LAP: priority = max(|TD error|, min_priority)^alpha")
    min_priority: float = hp(
        1.0, POSITIVE, "LAP: the least priority, and where the Huber loss turns linear"
    )
    zs_dim: int = hp(256, POSITIVE_INT, "SALE: the size of the embeddings zs and zsa")
    encoder_hidden_sizes: list[int] = hp(
        [256, 256], LAYERS, "SALE: hidden layers of the encoders f(s) and g(zs, a) (ELU)"
    )


#: Each algorithm's declaration, by its name (``algo=<name>``).
SCHEMAS: dict[str, type[Hyperparameters]] = {
    schema.NAME: schema
    for schema in (
        TD3Hyperparameters,
        DDPGHyperparameters,
        SACHyperparameters,
        CrossQHyperparameters,
        TD7Hyperparameters,
        PPOHyperparameters,
        ReinforceHyperparameters,
        DecisionTransformerHyperparameters,
        TD3BCHyperparameters,
    )
}


def schema_of(target: str) -> type[Hyperparameters] | None:
    """The declaration of the agent class ``target`` (an ``algo._target_``); None for a class
    walkers does not declare."""
    return next((schema for schema in SCHEMAS.values() if schema.AGENT == target), None)


def declared_since(algo: Mapping) -> dict:
    """The hyperparameters declared after ``algo`` (a run's stored ``algo`` config) was made,
    each with its declared default: the behaviour the run had before it existed (a resume and
    the check of a reference's update both take them so)."""
    schema = schema_of(algo.get("_target_", ""))
    if schema is None:
        return {}
    return {k: v for k, v in defaults(schema).items() if k not in algo}
