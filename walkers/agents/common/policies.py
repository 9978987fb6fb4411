"""The stochastic policy of the on-policy agents (REINFORCE, PPO), and PPO's initialisation.

Both use the parametrization of the reference PPO code (and of REINFORCE here): a Gaussian with a
state-dependent mean and a learned, state-independent log standard deviation, independent across
action dimensions. What differs is the mean network: REINFORCE's is the plain ReLU MLP of
:func:`walkers.agents.common.networks.mlp`; PPO's is built by :func:`orthogonal_mlp` (tanh,
orthogonal weights, zero biases), the initialisation its reference implementations use.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn
from torch.distributions import Normal

ACTIVATIONS = {"tanh": nn.Tanh, "relu": nn.ReLU}


class GaussianPolicy(nn.Module):
    """pi(a | s) = N(mean(s), diag(exp(log_std))^2), ``log_std`` a learned vector.

    ``log_std_min`` / ``log_std_max`` clamp the log-std when given (None: no bound).
    """

    def __init__(
        self,
        mean: nn.Module,
        act_dim: int,
        log_std_init: float,
        log_std_min: float | None = None,
        log_std_max: float | None = None,
    ):
        super().__init__()
        self.mean = mean
        self.log_std = nn.Parameter(torch.full((act_dim,), float(log_std_init)))
        self.log_std_min, self.log_std_max = log_std_min, log_std_max

    def forward(self, obs: torch.Tensor) -> Normal:
        log_std = self.log_std
        if self.log_std_min is not None or self.log_std_max is not None:
            log_std = log_std.clamp(self.log_std_min, self.log_std_max)
        # validate_args=False: the checks cost a third of a small update and prove nothing here
        return Normal(self.mean(obs), log_std.exp(), validate_args=False)


def orthogonal_mlp(
    in_dim: int,
    out_dim: int,
    hidden_sizes: Sequence[int],
    activation: str = "tanh",
    output_gain: float = 1.0,
) -> nn.Sequential:
    """An MLP initialised as PPO's reference code does: orthogonal weights (gain sqrt(2) for the
    hidden layers, ``output_gain`` for the last: 0.01 for a policy mean, 1 for a value), zero
    biases. ``activation``: ``tanh`` (the reference) or ``relu``."""
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation={activation!r} is not one of {sorted(ACTIVATIONS)}")
    layers: list[nn.Module] = []
    for width in hidden_sizes:
        layers += [_orthogonal(nn.Linear(in_dim, width), math.sqrt(2)), ACTIVATIONS[activation]()]
        in_dim = width
    layers.append(_orthogonal(nn.Linear(in_dim, out_dim), output_gain))
    return nn.Sequential(*layers)


def _orthogonal(layer: nn.Linear, gain: float) -> nn.Linear:
    nn.init.orthogonal_(layer.weight, gain)
    nn.init.zeros_(layer.bias)
    return layer
