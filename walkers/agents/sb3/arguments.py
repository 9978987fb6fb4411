"""``impl=sb3``: a walkers algorithm config as Stable-Baselines3's constructor arguments.

One table per algorithm says where each walkers hyperparameter goes in SB3 (README, "The
reference library as an arm", prints the same tables). A setting SB3 cannot express is refused
with a one-line error before anything starts; nothing is silently dropped. Pure: nothing here
imports SB3, so ``validate`` can check a config on a machine without it.

Fixed on both sides and not in the tables: one env, one gradient step per env step (off-policy),
ReLU hidden layers (off-policy), SB3's defaults for what walkers does not configure.
"""

from __future__ import annotations

from collections.abc import Mapping

from walkers.errors import ConfigError

#: The algorithms with a twin in Stable-Baselines3 (or its contrib package), as module.Class.
SB3_CLASSES = {
    "td3": "stable_baselines3.TD3",
    "ddpg": "stable_baselines3.DDPG",
    "sac": "stable_baselines3.SAC",
    "crossq": "sb3_contrib.CrossQ",
    "ppo": "stable_baselines3.PPO",
}

#: walkers key -> SB3 argument, per algorithm; "-" marks a walkers key with no SB3 argument that
#: is accepted only at the value given (SB3's own behaviour). Documentation and the checks below.
MAPPING: dict[str, dict[str, str]] = {
    "td3": {
        "lr": "learning_rate",
        "batch_size": "batch_size",
        "learning_starts": "learning_starts",
        "hidden_sizes": "policy_kwargs.net_arch (actor and critics)",
        "gamma": "gamma",
        "tau": "tau",
        "policy_noise": "target_policy_noise",
        "noise_clip": "target_noise_clip",
        "policy_delay": "policy_delay",
        "exploration_noise": "action_noise=NormalActionNoise(0, sigma)",
        "buffer_size": "buffer_size",
        "compile": "- (false only)",
        "capture": "- (false or auto: SB3 runs eagerly)",
        "precision": "- (fp32 only)",
    },
    "ddpg": {
        "lr": "learning_rate",
        "actor_lr": "- (null or = lr: SB3 has one learning rate)",
        "critic_lr": "- (null or = lr)",
        "batch_size": "batch_size",
        "learning_starts": "learning_starts",
        "hidden_sizes": "policy_kwargs.net_arch.pi",
        "critic_architecture": "- (mlp only)",
        "critic_hidden_sizes": "policy_kwargs.net_arch.qf (null: hidden_sizes)",
        "gamma": "gamma",
        "tau": "tau",
        "exploration_noise": "action_noise sigma",
        "noise_type": "action_noise: NormalActionNoise | OrnsteinUhlenbeckActionNoise (theta .15)",
        "buffer_size": "buffer_size",
        "compile": "- (false only)",
        "capture": "- (false or auto: SB3 runs eagerly)",
        "precision": "- (fp32 only)",
    },
    "sac": {
        "lr": "learning_rate (actor, critics and temperature)",
        "batch_size": "batch_size",
        "learning_starts": "learning_starts",
        "hidden_sizes": "policy_kwargs.net_arch (actor and critics)",
        "gamma": "gamma",
        "tau": "tau",
        "alpha_init": "ent_coef='auto_<alpha_init>'",
        "alpha_lr": "- (null or = lr: SB3's temperature shares the learning rate)",
        "target_entropy": "target_entropy (null: 'auto', -|A|)",
        "buffer_size": "buffer_size",
        "compile": "- (false only)",
        "capture": "- (false or auto: SB3 runs eagerly)",
        "precision": "- (fp32 only)",
    },
    "crossq": {
        "lr": "learning_rate (actor, critics and temperature)",
        "batch_size": "batch_size",
        "learning_starts": "learning_starts",
        "hidden_sizes": "policy_kwargs.net_arch.pi",
        "critic_hidden_sizes": "policy_kwargs.net_arch.qf",
        "gamma": "gamma",
        "adam_betas": "policy_kwargs.optimizer_kwargs.betas (actor and critics)",
        "policy_delay": "policy_delay",
        "renorm_momentum": "policy_kwargs.batch_norm_momentum",
        "renorm_warmup_steps": "policy_kwargs.renorm_warmup_steps",
        "alpha_init": "ent_coef='auto_<alpha_init>'",
        "alpha_lr": "- (null or = lr: the temperature shares the learning rate)",
        "target_entropy": "target_entropy (null: 'auto', -|A|)",
        "buffer_size": "buffer_size",
        "compile": "- (false only)",
        "capture": "- (false or auto: SB3 runs eagerly)",
    },
    "ppo": {
        "lr": "learning_rate",
        "anneal_lr": "learning_rate as a schedule: lr * (1 - progress)",
        "total_steps": "- (the run's budget: learn(total_timesteps))",
        "adam_eps": "policy_kwargs.optimizer_kwargs.eps",
        "n_steps": "n_steps",
        "num_envs": "- (1 only: the twin learns on one env)",
        "n_epochs": "n_epochs",
        "n_minibatches": "batch_size = n_steps / n_minibatches",
        "gamma": "gamma (and VecNormalize's return discount)",
        "gae_lambda": "gae_lambda",
        "clip_coef": "clip_range",
        "clip_value_loss": "clip_range_vf = clip_coef | None (SB3 clips V, not max of 2 losses)",
        "vf_coef": "vf_coef / 2 (SB3's value loss is mean (R-V)^2, walkers' 1/2 of it)",
        "ent_coef": "ent_coef",
        "max_grad_norm": "max_grad_norm (null: inf)",
        "target_kl": "- (null only: SB3 stops per minibatch at 1.5 x target_kl, walkers per epoch)",
        "normalize_advantages": "normalize_advantage",
        "hidden_sizes": "policy_kwargs.net_arch (pi and vf)",
        "activation": "policy_kwargs.activation_fn (tanh | relu)",
        "log_std_init": "policy_kwargs.log_std_init",
        "normalize_obs": "VecNormalize(norm_obs)",
        "clip_obs": "VecNormalize(clip_obs)",
        "normalize_reward": "VecNormalize(norm_reward)",
        "clip_reward": "VecNormalize(clip_reward)",
    },
}


def _refuse(algo: str, key: str, value, allowed: str) -> ConfigError:
    """A walkers setting that SB3's twin cannot express, as a one-line error."""
    return ConfigError(
        f"algo.{key}={value!r} cannot be expressed with impl=sb3 ({algo}): must be {allowed}"
    )


def check_algorithm(algo: str) -> None:
    if algo not in SB3_CLASSES:
        raise ConfigError(
            f"impl=sb3 is not available for algo={algo}: Stable-Baselines3 twins exist for "
            + ", ".join(SB3_CLASSES)
            + " (impl=walkers trains the others)"
        )


def sb3_arguments(algo: str, hp: Mapping) -> dict:
    """SB3's constructor arguments for walkers hyperparameters ``hp`` of ``algo``.

    Returns ``{"class": name, "kwargs": {...}, "noise": (kind, sigma) | None,
    "normalize": {...} | None, "net_arch": ..., "activation": ...}``: the parts that need SB3
    objects (noise, schedules, activation functions, VecNormalize) as plain descriptions, which
    :mod:`walkers.agents.sb3.twin` turns into objects. A setting SB3 cannot express raises
    :class:`~walkers.errors.ConfigError`.
    """
    check_algorithm(algo)
    unknown = sorted(set(hp) - set(MAPPING[algo]) - {"_target_", "name"})
    if unknown:
        raise ConfigError(
            f"algo.{unknown[0]} has no Stable-Baselines3 counterpart for {algo} "
            f"(impl=sb3 maps {', '.join(MAPPING[algo])})"
        )
    for key in ("compile", "capture"):
        if hp.get(key) is True:
            allowed = "false" if key == "compile" else "false or auto"
            raise _refuse(algo, key, hp[key], f"{allowed} (SB3 runs eagerly)")
    if hp.get("precision", "fp32") != "fp32":
        raise _refuse(algo, "precision", hp["precision"], "fp32 (SB3 runs in fp32)")
    build = {"ppo": _ppo, "sac": _sac, "crossq": _crossq}
    return build.get(algo, _deterministic_actor_critic)(algo, hp)


def _off_policy_common(hp: Mapping) -> dict:
    common = {
        "learning_rate": hp["lr"],
        "batch_size": hp["batch_size"],
        "learning_starts": hp["learning_starts"],
        "gamma": hp["gamma"],
        "buffer_size": hp["buffer_size"],
        "train_freq": 1,
        "gradient_steps": 1,
    }
    return common | ({"tau": hp["tau"]} if "tau" in hp else {})  # CrossQ has no targets


def _deterministic_actor_critic(algo: str, hp: Mapping) -> dict:
    """TD3, and DDPG (SB3's DDPG is its TD3 with one critic, no smoothing, no delay)."""
    kwargs = _off_policy_common(hp)
    net_arch = list(hp["hidden_sizes"])
    noise = ("gaussian", hp["exploration_noise"])
    if algo == "td3":
        kwargs |= {
            "target_policy_noise": hp["policy_noise"],
            "target_noise_clip": hp["noise_clip"],
            "policy_delay": hp["policy_delay"],
        }
    else:
        for key in ("actor_lr", "critic_lr"):
            if hp.get(key) is not None and hp[key] != hp["lr"]:
                raise _refuse(algo, key, hp[key], "null or equal to algo.lr")
        if hp.get("critic_architecture", "mlp") != "mlp":
            raise _refuse(algo, "critic_architecture", hp["critic_architecture"], "mlp")
        critic = hp.get("critic_hidden_sizes") or net_arch
        net_arch = {"pi": net_arch, "qf": list(critic)}
        noise = (hp.get("noise_type", "gaussian"), hp["exploration_noise"])
    return {"class": SB3_CLASSES[algo], "kwargs": kwargs, "noise": noise, "net_arch": net_arch}


def _soft_actor_critic(algo: str, hp: Mapping) -> dict:
    """SAC's and CrossQ's arguments: the common ones and the temperature's."""
    if hp.get("alpha_lr") is not None and hp["alpha_lr"] != hp["lr"]:
        raise _refuse(algo, "alpha_lr", hp["alpha_lr"], "null or equal to algo.lr")
    target = hp.get("target_entropy")
    return _off_policy_common(hp) | {
        "ent_coef": f"auto_{hp['alpha_init']}",
        "target_entropy": "auto" if target is None else float(target),
    }


def _sac(algo: str, hp: Mapping) -> dict:
    kwargs = _soft_actor_critic(algo, hp)
    return {
        "class": SB3_CLASSES[algo],
        "kwargs": kwargs,
        "noise": None,
        "net_arch": list(hp["hidden_sizes"]),
    }


def _crossq(algo: str, hp: Mapping) -> dict:
    kwargs = _soft_actor_critic(algo, hp) | {"policy_delay": hp["policy_delay"]}
    net_arch = {"pi": list(hp["hidden_sizes"]), "qf": list(hp["critic_hidden_sizes"])}
    return {
        "class": SB3_CLASSES[algo],
        "kwargs": kwargs,
        "noise": None,
        "net_arch": net_arch,
        "policy_kwargs": {
            "optimizer_kwargs": {"betas": tuple(hp["adam_betas"])},
            "batch_norm_momentum": hp["renorm_momentum"],
            "renorm_warmup_steps": hp["renorm_warmup_steps"],
        },
    }


def _ppo(algo: str, hp: Mapping) -> dict:
    if hp.get("target_kl") is not None:
        raise _refuse(
            algo, "target_kl", hp["target_kl"], "null (SB3's early stop is per minibatch)"
        )
    if hp.get("num_envs", 1) != 1:
        raise _refuse(algo, "num_envs", hp["num_envs"], "1 (the twin learns on one env)")
    n_steps, n_minibatches = hp["n_steps"], hp["n_minibatches"]
    if n_steps % n_minibatches:
        raise _refuse(algo, "n_minibatches", n_minibatches, f"a divisor of algo.n_steps={n_steps}")
    if hp["activation"] not in ("tanh", "relu"):
        raise _refuse(algo, "activation", hp["activation"], "tanh or relu")
    kwargs = {
        "n_steps": n_steps,
        "n_epochs": hp["n_epochs"],
        "batch_size": n_steps // n_minibatches,
        "gamma": hp["gamma"],
        "gae_lambda": hp["gae_lambda"],
        "clip_range": hp["clip_coef"],
        "clip_range_vf": hp["clip_coef"] if hp["clip_value_loss"] else None,
        "vf_coef": hp["vf_coef"] / 2,
        "ent_coef": hp["ent_coef"],
        "max_grad_norm": float("inf") if hp["max_grad_norm"] is None else hp["max_grad_norm"],
        "normalize_advantage": hp["normalize_advantages"],
    }
    normalize = None
    if hp["normalize_obs"] or hp["normalize_reward"]:
        normalize = {
            "norm_obs": hp["normalize_obs"],
            "norm_reward": hp["normalize_reward"],
            "clip_obs": hp["clip_obs"],
            "clip_reward": hp["clip_reward"],
            "gamma": hp["gamma"],
        }
    return {
        "class": SB3_CLASSES[algo],
        "kwargs": kwargs,
        "lr": hp["lr"],
        "anneal_lr": hp["anneal_lr"],
        "adam_eps": hp["adam_eps"],
        "log_std_init": hp["log_std_init"],
        "activation": hp["activation"],
        "net_arch": {"pi": list(hp["hidden_sizes"]), "vf": list(hp["hidden_sizes"])},
        "normalize": normalize,
        "noise": None,
    }
