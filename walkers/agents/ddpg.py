"""DDPG (Lillicrap et al. 2016) as the TD3 paper's "our DDPG", plus the tutorial's variants."""

from __future__ import annotations

from walkers.agents.td3 import TD3


class DDPG(TD3):
    """TD3 with its three ideas off (the class attributes below): one critic, no target policy
    smoothing, the actor and targets updated at every critic update. Its constructor takes no
    ``policy_noise``, ``noise_clip`` or ``policy_delay`` (TD3's refuses them for DDPG).

    Otherwise TD3 (declared in :mod:`walkers.agents.declarations.schemas`), including the tutorial's
    variants: ``critic_architecture=layernorm_branch`` (state layers ``critic_hidden_sizes`` of
    Linear + LayerNorm + ReLU, the action merged at the last hidden layer) and ``noise_type=ou``
    (Ornstein-Uhlenbeck exploration).
    """

    num_critics = 1
    target_smoothing = False
    delayed_updates = False
