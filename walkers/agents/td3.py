"""TD3: Twin Delayed Deep Deterministic policy gradient (Fujimoto, van Hoof, Meger 2018)."""

from __future__ import annotations

from walkers.agents.actor_critic import ActorCritic


class TD3(ActorCritic):
    """Clipped double-Q (two critics), target policy smoothing, delayed policy updates.

    Hyperparameters (``lr``, ``batch_size``, ``policy_noise``, ...) are :class:`ActorCritic`'s,
    whose defaults are the paper's; each is documented in ``conf/algo/td3.yaml``.
    """

    def __init__(self, obs_dim, action_low, action_high, **hyperparameters):
        super().__init__(obs_dim, action_low, action_high, num_critics=2, **hyperparameters)
