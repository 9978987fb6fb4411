"""Networks: MLPs, and the actors and critics of DDPG/TD3/SAC as *ensembles*.

Every layer of an ensemble holds the weights of all its members stacked along a leading
dimension and runs them with one batched matmul. TD3's and SAC's twin critics are an ensemble of
two; DDPG's single critic an ensemble of one; a single agent's actor an ensemble of one, a seed
population's actors an ensemble of K (so a member's weights have one layout everywhere).
Members share no parameters, so optimizing an ensemble with an elementwise optimizer (Adam)
trains each member independently.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn
from torch.nn import functional as F

#: every member of an ensemble (the default of ``members``)
ALL = slice(None)


def mlp(in_dim: int, out_dim: int, hidden_sizes: Sequence[int]) -> nn.Sequential:
    """Linear-ReLU stack with a linear output layer."""
    layers: list[nn.Module] = []
    for width in hidden_sizes:
        layers += [nn.Linear(in_dim, width), nn.ReLU()]
        in_dim = width
    layers.append(nn.Linear(in_dim, out_dim))
    return nn.Sequential(*layers)


class EnsembleLinear(nn.Module):
    """``n`` independent linear layers applied with one batched matmul.

    Input ``(n, batch, in)``, or ``(batch, in)`` shared by all members; output ``(n, batch, out)``.
    ``members`` selects a subset (TD3's actor loss reads only the first critic). Initialised like
    ``nn.Linear`` member by member. A network's output layer (``head``) runs in fp32 under
    bfloat16 autocast (``algo.precision=bf16``), so the losses read fp32 values (Q, actions,
    SAC's mean and log-std): the hidden layers' matmuls in bfloat16, not the answer's rounding.
    """

    def __init__(self, n: int, in_dim: int, out_dim: int, head: bool = False):
        super().__init__()
        bound = 1 / math.sqrt(in_dim)
        self.weight = nn.Parameter(torch.empty(n, in_dim, out_dim).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(n, 1, out_dim).uniform_(-bound, bound))
        self.head = head

    def forward(self, x: torch.Tensor, members: slice = ALL) -> torch.Tensor:
        # all members: the parameters themselves (an index would add a view and its backward)
        weight, bias = (
            (self.weight, self.bias)
            if members == ALL
            else (self.weight[members], self.bias[members])
        )
        if x.dim() == 2:
            x = x.expand(weight.shape[0], *x.shape)
        if self.head and torch.is_autocast_enabled(x.device.type):
            with torch.autocast(x.device.type, enabled=False):
                return torch.baddbmm(bias, x.float(), weight)
        return torch.baddbmm(bias, x, weight)


class EnsembleActor(nn.Module):
    """``n`` independent deterministic policies pi_i(s) = tanh(MLP_i(s)) scaled onto the action
    bounds, one batched matmul a layer (``n`` = 1 for a single agent, K for a seed population).

    Input ``(n, batch, obs)`` (or ``(batch, obs)`` shared); output ``(n, batch, act)``; ``members``
    selects a subset.
    """

    def __init__(self, n, obs_dim, act_dim, hidden_sizes, action_low, action_high):
        super().__init__()
        dims = [obs_dim, *hidden_sizes, act_dim]
        self.layers = nn.ModuleList(
            EnsembleLinear(n, a, b, head=i == len(dims) - 2)
            for i, (a, b) in enumerate(zip(dims[:-1], dims[1:], strict=True))
        )
        low = torch.as_tensor(action_low, dtype=torch.float32)
        high = torch.as_tensor(action_high, dtype=torch.float32)
        # derived from the env, not learned: not part of the state dict
        self.register_buffer("action_scale", (high - low) / 2, persistent=False)
        self.register_buffer("action_bias", (high + low) / 2, persistent=False)

    def forward(self, obs: torch.Tensor, members: slice = slice(None)) -> torch.Tensor:
        x = obs
        for layer in self.layers[:-1]:
            x = layer(x, members).relu_()  # in place: the matmul's fresh output
        return torch.tanh(self.layers[-1](x, members)) * self.action_scale + self.action_bias


def tanh_log_det_jacobian(u: torch.Tensor) -> torch.Tensor:
    """log(1 - tanh(u)^2), elementwise, computed stably as 2 (log 2 - u - softplus(-2u)).

    (1 - tanh(u)^2 = 4 / (e^u + e^-u)^2, whose log is the right-hand side; the naive form is
    log(0) = -inf once tanh(u) rounds to +-1, i.e. for |u| >~ 9 in float32.)
    """
    return 2.0 * (math.log(2.0) - u - F.softplus(-2.0 * u))


class EnsembleGaussianActor(EnsembleActor):
    """``n`` independent squashed Gaussian policies (SAC): a = tanh(u) scaled onto the action
    bounds, u ~ N(mu_i(s), sigma_i(s)^2), with mean and log-std from one MLP per member (the
    last layer outputs both, so every layer is one batched matmul for all members).

    ``forward`` is the deterministic policy tanh(mu(s)) (evaluation, a member's greedy act);
    :meth:`sample` the reparameterized sample and its log-probability. log sigma is clamped to
    [``LOG_STD_MIN``, ``LOG_STD_MAX``] (the reference implementations' bounds).
    """

    LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0

    def __init__(self, n, obs_dim, act_dim, hidden_sizes, action_low, action_high):
        # the deterministic actor's layers and action bounds, with a head twice as wide: the
        # mean and the log-std
        super().__init__(n, obs_dim, 2 * act_dim, hidden_sizes, action_low, action_high)

    def distribution(
        self, obs: torch.Tensor, members: slice = slice(None)
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """mu(s) and log sigma(s) (clamped), each ``(n, batch, act)``."""
        x = obs
        for layer in self.layers[:-1]:
            x = layer(x, members).relu_()
        mean, log_std = self.layers[-1](x, members).chunk(2, dim=-1)
        return mean, log_std.clamp(self.LOG_STD_MIN, self.LOG_STD_MAX)

    def forward(self, obs: torch.Tensor, members: slice = slice(None)) -> torch.Tensor:
        """The deterministic policy: tanh(mu(s)), scaled."""
        mean, _ = self.distribution(obs, members)
        return torch.tanh(mean) * self.action_scale + self.action_bias

    def sample(
        self, obs: torch.Tensor, eps: torch.Tensor, members: slice = slice(None)
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """a = tanh(mu + sigma * eps) scaled, for given eps ~ N(0, I) ``(n, batch, act)``, and
        log pi(a|s) ``(n, batch)``: the Gaussian's log-density at u = mu + sigma * eps minus
        sum_k log(1 - tanh(u_k)^2) (change of variables through tanh; SAC paper, appendix C).

        The density is that of the squashed action in [-1, 1]^act (as the reference
        implementations, whose envs act in [-1, 1]); the constant -sum log(action_scale) of
        the final rescaling is left out, so the target entropy keeps its meaning for any bounds.
        """
        mean, log_std = self.distribution(obs, members)
        u = mean + log_std.exp() * eps
        gaussian = (-0.5 * eps.pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(dim=-1)
        log_prob = gaussian - tanh_log_det_jacobian(u).sum(dim=-1)
        return torch.tanh(u) * self.action_scale + self.action_bias, log_prob


class Temperature(nn.Module):
    """SAC's learned entropy temperature, one per member: alpha_i = exp(log_alpha_i), ``(n,)``.

    Learned in log space (positive, and the reference implementations' parameterization)."""

    def __init__(self, n: int, initial: float = 1.0):
        super().__init__()
        self.log_alpha = nn.Parameter(torch.full((n,), math.log(initial)))

    def forward(self) -> torch.Tensor:
        """alpha ``(n,)``, detached: the critic target and actor loss treat it as a constant."""
        return self.log_alpha.detach().exp()


class EnsembleLayerNorm(nn.Module):
    """LayerNorm over the feature dimension with a separate affine transform per member."""

    def __init__(self, n: int, dim: int):
        super().__init__()
        self.weight = nn.Parameter(torch.ones(n, 1, dim))
        self.bias = nn.Parameter(torch.zeros(n, 1, dim))

    def forward(self, x: torch.Tensor, members: slice = slice(None)) -> torch.Tensor:
        return torch.addcmul(
            self.bias[members], F.layer_norm(x, x.shape[-1:]), self.weight[members]
        )


class MLPCriticEnsemble(nn.Module):
    """``n`` Q-networks Q_i(s, a) = MLP_i([s, a]) -> tensor ``(n, batch)``.

    The architecture of the TD3 paper (and of "our DDPG" there).
    """

    def __init__(self, obs_dim: int, act_dim: int, hidden_sizes: Sequence[int], n: int = 2):
        super().__init__()
        dims = [obs_dim + act_dim, *hidden_sizes]
        self.hidden = nn.ModuleList(
            EnsembleLinear(n, a, b) for a, b in zip(dims[:-1], dims[1:], strict=True)
        )
        self.out = EnsembleLinear(n, dims[-1], 1, head=True)

    def forward(self, obs, action, members: slice = slice(None)) -> torch.Tensor:
        x = torch.cat([obs, action], dim=-1)
        for layer in self.hidden:
            x = layer(x, members).relu_()
        return self.out(x, members).squeeze(-1)


class BranchCriticEnsemble(nn.Module):
    """The tutorial's configurable DDPG critic, as ``n`` members -> ``(n, batch)``.

    The state goes through ``hidden_sizes`` layers of Linear + LayerNorm + ReLU; the action enters
    through its own linear layer at the last hidden width; the two branches merge by
    ``relu(state_branch + relu(action_branch))`` and a linear head gives Q(s, a).
    """

    def __init__(self, obs_dim: int, act_dim: int, hidden_sizes: Sequence[int], n: int = 1):
        super().__init__()
        dims = [obs_dim, *hidden_sizes]
        self.state_layers = nn.ModuleList(
            EnsembleLinear(n, a, b) for a, b in zip(dims[:-1], dims[1:], strict=True)
        )
        self.state_norms = nn.ModuleList(EnsembleLayerNorm(n, b) for b in dims[1:])
        self.action_layer = EnsembleLinear(n, act_dim, dims[-1])
        self.out = EnsembleLinear(n, dims[-1], 1, head=True)

    def forward(self, obs, action, members: slice = slice(None)) -> torch.Tensor:
        x = obs
        for layer, norm in zip(self.state_layers, self.state_norms, strict=True):
            x = F.relu(norm(layer(x, members), members))
        x = F.relu(x + F.relu(self.action_layer(action, members)))
        return self.out(x, members).squeeze(-1)


CRITIC_ARCHITECTURES = {"mlp": MLPCriticEnsemble, "layernorm_branch": BranchCriticEnsemble}


def make_critic(architecture: str, obs_dim, act_dim, hidden_sizes, n: int) -> nn.Module:
    if architecture not in CRITIC_ARCHITECTURES:
        raise ValueError(
            f"critic_architecture={architecture!r} is not one of {sorted(CRITIC_ARCHITECTURES)}"
        )
    return CRITIC_ARCHITECTURES[architecture](obs_dim, act_dim, hidden_sizes, n)


@torch.no_grad()
def soft_update(target: nn.Module, source: nn.Module, tau: float) -> None:
    """Polyak averaging theta' <- theta' + tau * (theta - theta'), one fused foreach op."""
    torch._foreach_lerp_(list(target.parameters()), list(source.parameters()), tau)
