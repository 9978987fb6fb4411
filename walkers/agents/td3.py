"""TD3: Twin Delayed Deep Deterministic policy gradient (Fujimoto, van Hoof, Meger 2018)."""

from __future__ import annotations

from walkers.agents.actor_critic import ActorCritic


class TD3(ActorCritic):
    """Clipped double-Q (two critics), target policy smoothing, delayed policy updates.

    Hyperparameters are documented in ``conf/algo/td3.yaml``; the defaults here are the paper's.
    """

    def __init__(
        self,
        obs_dim,
        action_low,
        action_high,
        *,
        lr=3e-4,
        batch_size=256,
        learning_starts=25_000,
        hidden_sizes=(256, 256),
        gamma=0.99,
        tau=0.005,
        policy_noise=0.2,
        noise_clip=0.5,
        policy_delay=2,
        exploration_noise=0.1,
        buffer_size=1_000_000,
        device="cpu",
        seed=0,
    ):
        super().__init__(
            obs_dim,
            action_low,
            action_high,
            lr=lr,
            batch_size=batch_size,
            learning_starts=learning_starts,
            hidden_sizes=hidden_sizes,
            gamma=gamma,
            tau=tau,
            num_critics=2,
            policy_noise=policy_noise,
            noise_clip=noise_clip,
            policy_delay=policy_delay,
            exploration_noise=exploration_noise,
            buffer_size=buffer_size,
            device=device,
            seed=seed,
        )
