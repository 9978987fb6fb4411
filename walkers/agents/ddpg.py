"""DDPG (Lillicrap et al. 2016) as the TD3 paper's "our DDPG", plus the tutorial's variants."""

from __future__ import annotations

from walkers.agents.actor_critic import ActorCritic


class DDPG(ActorCritic):
    """One critic, no target smoothing, actor and targets updated every step.

    ``critic_architecture``: ``mlp`` (TD3's networks, the tutorial's "same structure" DDPG) or
    ``layernorm_branch`` (the tutorial's DDPG: state layers ``critic_hidden_sizes`` of
    Linear + LayerNorm + ReLU, the action merged at the last hidden layer).
    ``noise_type``: ``gaussian`` or ``ou`` (Ornstein-Uhlenbeck) exploration.
    """

    def __init__(
        self,
        obs_dim,
        action_low,
        action_high,
        *,
        lr=3e-4,
        actor_lr=None,
        critic_lr=None,
        batch_size=256,
        learning_starts=25_000,
        hidden_sizes=(256, 256),
        critic_architecture="mlp",
        critic_hidden_sizes=None,
        gamma=0.99,
        tau=0.005,
        exploration_noise=0.1,
        noise_type="gaussian",
        buffer_size=1_000_000,
        device="cpu",
        seed=0,
    ):
        super().__init__(
            obs_dim,
            action_low,
            action_high,
            lr=lr,
            actor_lr=actor_lr,
            critic_lr=critic_lr,
            batch_size=batch_size,
            learning_starts=learning_starts,
            hidden_sizes=hidden_sizes,
            critic_architecture=critic_architecture,
            critic_hidden_sizes=critic_hidden_sizes,
            gamma=gamma,
            tau=tau,
            num_critics=1,
            policy_noise=0.0,
            noise_clip=0.0,
            policy_delay=1,
            exploration_noise=exploration_noise,
            noise_type=noise_type,
            buffer_size=buffer_size,
            device=device,
            seed=seed,
        )
