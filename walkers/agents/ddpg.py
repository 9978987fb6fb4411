"""DDPG (Lillicrap et al. 2016) as the TD3 paper's "our DDPG", plus the tutorial's variants."""

from __future__ import annotations

from walkers.agents.actor_critic import ActorCritic


class DDPG(ActorCritic):
    """One critic, no target smoothing, actor and targets updated every step.

    Otherwise :class:`ActorCritic` (documented in ``conf/algo/ddpg.yaml``), including the
    tutorial's variants: ``critic_architecture=layernorm_branch`` (state layers
    ``critic_hidden_sizes`` of Linear + LayerNorm + ReLU, the action merged at the last hidden
    layer) and ``noise_type=ou`` (Ornstein-Uhlenbeck exploration).
    """

    def __init__(self, obs_dim, action_low, action_high, **hyperparameters):
        super().__init__(
            obs_dim,
            action_low,
            action_high,
            num_critics=1,
            policy_noise=0.0,
            noise_clip=0.0,
            policy_delay=1,
            **hyperparameters,
        )
