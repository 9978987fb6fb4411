"""``impl=sb3``: a Stable-Baselines3 model behind walkers' Agent interface.

SB3 trains with its own loop (``model.learn``: its collection, its updates, its VecNormalize);
walkers only drives that loop (:func:`walkers.training.loops.train_sb3`) and, through this
adapter, acts greedily for its evaluations and videos, and saves and restores everything a
resume needs (the model, the replay buffer, the normalization statistics, SB3's random streams).
So an SB3 run is evaluated, logged, checkpointed and summarized exactly as a walkers run is.

SB3 is an optional dependency (``pip install -e '.[sb3]'``): it is imported when a twin is built.
"""

from __future__ import annotations

import importlib
import io
import random
from collections.abc import Mapping, Sequence

import gymnasium as gym
import numpy as np
import torch

from walkers.agents.base import Policy, resolve_device
from walkers.agents.sb3.arguments import sb3_arguments
from walkers.errors import ConfigError
from walkers.seeding import stream_seeds

INSTALL_HINT = "pip install -e '.[sb3]' (or make install, which includes it)"

#: SB3's logger keys -> walkers' metric names (and a scale to the same quantity).
SB3_METRICS = {
    "train/critic_loss": ("loss/critic", 1.0),
    "train/actor_loss": ("loss/actor", 1.0),
    "train/ent_coef": ("train/alpha", 1.0),
    "train/ent_coef_loss": ("loss/alpha", 1.0),
    "train/policy_gradient_loss": ("loss/policy", 1.0),
    "train/value_loss": ("loss/value", 0.5),  # SB3: mean (R-V)^2; walkers: 1/2 of it
    "train/entropy_loss": ("train/entropy", -1.0),
    "train/approx_kl": ("train/approx_kl", 1.0),
    "train/clip_fraction": ("train/clip_fraction", 1.0),
    "train/explained_variance": ("train/explained_variance", 1.0),
    "train/learning_rate": ("train/lr", 1.0),
    "train/std": ("train/std", 1.0),
}


def import_sb3():
    """The ``stable_baselines3`` module, or a one-line error saying how to install it."""
    try:
        import stable_baselines3
    except ImportError:
        raise ConfigError(f"impl=sb3 needs Stable-Baselines3: {INSTALL_HINT}") from None
    return stable_baselines3


def reference_class(path: str) -> type:
    """The reference library's class ``module.Class`` (sb3-contrib's ships with the ``sb3``
    extra), or a one-line error saying how to install it."""
    module, name = path.rsplit(".", 1)
    try:
        return getattr(importlib.import_module(module), name)
    except ImportError:
        raise ConfigError(f"impl=sb3 needs {module}: {INSTALL_HINT}") from None


class SB3Twin(Policy):
    """SB3's twin of walkers algorithm ``algo`` with walkers hyperparameters ``hyperparameters``.

    The model is created by :meth:`attach` (training: SB3 needs its env) or by
    :meth:`load_state_dict` (a checkpoint: acting needs no env). It learns inside SB3's own
    ``learn()`` (``walkers.training.loops.train_sb3``): of walkers' interfaces it is a policy.
    """

    trains_itself = True

    def __init__(
        self,
        algo: str,
        hyperparameters: Mapping,
        obs_dim: int,
        action_low: Sequence[float],
        action_high: Sequence[float],
        seed: int = 0,
        device: str = "auto",
    ):
        self.sb3 = import_sb3()
        self.algo = algo
        self.arguments = sb3_arguments(algo, hyperparameters)
        self.cls = reference_class(self.arguments["class"])
        self.device = resolve_device(device)
        self.seed = seed
        self.obs_dim = obs_dim
        self.action_low, self.action_high = np.asarray(action_low), np.asarray(action_high)
        self.model = None
        self.vec_env = None  # SB3's view of the training env (VecNormalize on top for PPO)
        self.normalization: dict | None = None  # VecNormalize's state, for acting without an env
        self.notes: dict[str, str] = {}

    # --- building ------------------------------------------------------------------------------
    def attach(self, env: gym.Env, total_steps: int) -> None:
        """Build the model on the training ``env`` (one env, SB3's DummyVecEnv around it)."""
        from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

        a = self.arguments
        self.vec_env = DummyVecEnv([lambda: env])
        if a.get("normalize"):
            self.vec_env = VecNormalize(self.vec_env, **a["normalize"])
        self.total_steps = total_steps
        self.model = self.cls(
            "MlpPolicy",
            self.vec_env,
            **a["kwargs"],
            **self._objects(),
            seed=stream_seeds(self.seed, "policy")[0],  # SB3's one seed for all its streams
            device=self.device,
            verbose=0,
        )
        self._log_in_memory()

    def _objects(self) -> dict:
        """The arguments that are SB3 objects: noise, schedules, activation, optimizer."""
        a = self.arguments
        out: dict = {"policy_kwargs": {"net_arch": a["net_arch"]} | a.get("policy_kwargs", {})}
        n = len(self.action_low)
        if a["noise"] is not None:
            kind, sigma = a["noise"]
            noises = self.sb3.common.noise
            cls = noises.OrnsteinUhlenbeckActionNoise if kind == "ou" else noises.NormalActionNoise
            out["action_noise"] = cls(mean=np.zeros(n), sigma=sigma * np.ones(n))
        if a["class"].endswith(".PPO"):
            lr = a["lr"]
            out["learning_rate"] = (lambda progress: lr * progress) if a["anneal_lr"] else lr
            out["policy_kwargs"] |= {
                "activation_fn": {"tanh": torch.nn.Tanh, "relu": torch.nn.ReLU}[a["activation"]],
                "log_std_init": a["log_std_init"],
                "optimizer_kwargs": {"eps": a["adam_eps"]},
            }
        return out

    def _log_in_memory(self) -> None:
        """SB3 records its training values in memory only (read by ``latest_losses``); left to
        itself, every ``learn`` call would make a ``$TMPDIR/SB3-<time>`` folder."""
        from stable_baselines3.common.logger import Logger

        self.model.set_logger(Logger(folder=None, output_formats=[]))

    @property
    def vec_normalize(self):
        from stable_baselines3.common.vec_env import VecNormalize

        return self.vec_env if isinstance(self.vec_env, VecNormalize) else None

    # --- acting (evaluation, videos) -----------------------------------------------------------
    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        if explore:
            raise NotImplementedError("an SB3 twin explores inside SB3's own loop")
        obs = self._normalized(np.asarray(obs, dtype=np.float32))
        action, _ = self.model.predict(obs, deterministic=True)
        return action

    def _normalized(self, obs: np.ndarray) -> np.ndarray:
        if self.vec_normalize is not None:
            return self.vec_normalize.normalize_obs(obs)
        s = self.normalization
        if s is None or not s["norm_obs"]:
            return obs
        rms = s["obs_rms"]
        return np.clip(
            (obs - rms.mean) / np.sqrt(rms.var + s["epsilon"]), -s["clip_obs"], s["clip_obs"]
        ).astype(np.float32)

    def latest_losses(self) -> dict[str, torch.Tensor]:
        """SB3's latest recorded training values, under walkers' metric names."""
        recorded = self.model.logger.name_to_value
        return {
            name: torch.tensor(float(recorded[key]) * scale)
            for key, (name, scale) in SB3_METRICS.items()
            if key in recorded
        }

    # --- checkpoints ---------------------------------------------------------------------------
    def state_dict(self, with_buffer: bool = False) -> dict:
        blob = io.BytesIO()
        self.model.save(blob)
        buffer = getattr(self.model, "replay_buffer", None)
        vec_normalize = self.vec_normalize
        return {
            "impl": "sb3",
            "model": blob.getvalue(),
            "replay_buffer": buffer if with_buffer else None,
            "normalization": (
                vec_normalize.__getstate__() if vec_normalize is not None else self.normalization
            ),
            "action_noise": getattr(self.model, "action_noise", None),
            "rng": {
                "numpy": np.random.get_state(),
                "python": random.getstate(),
                "action_space": self.model.action_space.np_random.bit_generator.state,
            },
        }

    def load_state_dict(self, state: dict) -> None:
        self.model = self.cls.load(
            io.BytesIO(state["model"]), env=self.vec_env, device=self.device, force_reset=True
        )
        self._log_in_memory()
        self.normalization = state["normalization"]
        if self.vec_normalize is not None and self.normalization is not None:
            # VecNormalize's pickled state leaves out ``returns`` (the running discounted
            # return): SB3 resets the env on resume (force_reset), which zeroes it anyway
            for key in ("obs_rms", "ret_rms"):
                setattr(self.vec_normalize, key, self.normalization[key])
        if state["action_noise"] is not None:
            self.model.action_noise = state["action_noise"]
        rng = state["rng"]
        np.random.set_state(rng["numpy"])
        random.setstate(rng["python"])
        self.model.action_space.np_random.bit_generator.state = rng["action_space"]
        self.notes = {}
        if hasattr(self.model, "replay_buffer"):
            self._restore_buffer(state["replay_buffer"])
        elif self.model.num_timesteps % self.model.n_steps:
            self.notes["walkers.rollout_recollected"] = (
                f"from step {self.model.num_timesteps}: SB3 starts a new rollout on resume"
            )

    def _restore_buffer(self, buffer) -> None:
        if self.vec_env is None:  # acting only: no buffer needed
            return
        model = self.model
        if buffer is not None:
            buffer.device = model.device
            model.replay_buffer = buffer
            return
        # the uploaded checkpoint has no buffer: refill it with uniform random actions first
        start = model.num_timesteps
        model.learning_starts = start + model.learning_starts
        self.notes["walkers.buffer_refill"] = (
            f"steps {start}-{model.learning_starts} (uniform random: SB3's warm-up)"
        )

    def resume_notes(self) -> dict[str, str]:
        return self.notes
