"""DDPG (Lillicrap et al. 2016) as the TD3 paper's "our DDPG", plus the tutorial's variants."""

from __future__ import annotations

from walkers.agents.td3 import TD3


class DDPG(TD3):
    """TD3 with its three ideas off (the class attributes below): one critic, no target policy
    smoothing, the actor and targets updated at every critic update. Its constructor takes no
    ``policy_noise``, ``noise_clip`` or ``policy_delay``.

    Otherwise TD3 (documented in ``conf/algo/ddpg.yaml``), including the tutorial's variants:
    ``critic_architecture=layernorm_branch`` (state layers ``critic_hidden_sizes`` of Linear +
    LayerNorm + ReLU, the action merged at the last hidden layer) and ``noise_type=ou``
    (Ornstein-Uhlenbeck exploration).
    """

    num_critics = 1
    target_smoothing = False
    delayed_updates = False

    def __init__(
        self,
        obs_dim,
        action_low,
        action_high,
        *,
        exploration_noise: float = 0.1,
        noise_type: str = "gaussian",
        **core,
    ):
        for knob in ("policy_noise", "noise_clip", "policy_delay"):
            if knob in core:
                raise TypeError(
                    f"DDPG.__init__() got an unexpected keyword argument {knob!r} "
                    "(DDPG is TD3 without target smoothing or delayed updates)"
                )
        super().__init__(
            obs_dim,
            action_low,
            action_high,
            exploration_noise=exploration_noise,
            noise_type=noise_type,
            **core,
        )
