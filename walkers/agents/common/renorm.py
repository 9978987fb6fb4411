"""Batch Renormalization (Ioffe 2017) for ensembles, and CrossQ's networks built with it.

CrossQ (:mod:`walkers.agents.crossq`) normalizes the inputs of every linear layer of its actor and
critics, as sb3-contrib's CrossQ does (``BatchRenorm1d`` before each ``Linear``, and once more
before the actor's heads). Batch Renormalization is BatchNorm that, after ``warmup_steps``
training passes, normalizes with the running statistics corrected towards the batch's (r, d,
clipped to ``r_max``, ``d_max``), so an outlier batch late in training cannot throw it off.

In training mode (``module.train()``) a layer normalizes with batch statistics and moves its
running statistics; in evaluation mode (``module.eval()``, how CrossQ acts and evaluates) it
normalizes with the running statistics alone. The agent switches modes around each pass; the
networks stay in evaluation mode otherwise.

Every statistic has a leading member dimension, like the weights of
:class:`~walkers.agents.common.networks.EnsembleLinear`: members are independent seeds and critics,
so each keeps its own statistics (and a population member's checkpoint is its slice of them).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import torch
from torch import nn
from torch.nn import functional as F

from walkers.agents.common.networks import EnsembleGaussianActor, EnsembleLinear


class EnsembleBatchRenorm(nn.Module):
    """Batch Renormalization of ``(n, batch, features)`` inputs, statistics over the batch of each
    member. The running statistics move by ``momentum`` at each training pass (sb3-contrib's
    convention: 0.01; the JAX reference writes 0.99 for the same thing)."""

    R_MAX, D_MAX = 3.0, 5.0  # the clips of the correction (sb3-contrib's, constant after warm-up)

    def __init__(self, n: int, features: int, momentum: float, warmup_steps: int, eps=1e-3):
        super().__init__()
        self.momentum, self.warmup_steps, self.eps = momentum, warmup_steps, eps
        self.scale = nn.Parameter(torch.ones(n, 1, features))
        self.bias = nn.Parameter(torch.zeros(n, 1, features))
        self.register_buffer("running_mean", torch.zeros(n, 1, features))
        self.register_buffer("running_var", torch.ones(n, 1, features))
        self.register_buffer("steps", torch.zeros(n, dtype=torch.long))  # training passes

    def forward(self, x: torch.Tensor, members: slice = slice(None)) -> torch.Tensor:
        scale, bias = self.scale[members], self.bias[members]
        if not self.training:
            mean, var = self.running_mean[members], self.running_var[members]
        else:
            if members != slice(None):
                raise ValueError("batch statistics are learned by all members together")
            mean, var = self._training_statistics(x)
        # scale * (x - mean) / sqrt(var + eps) + bias, with the per-feature factors folded
        # first: two passes over x instead of four (the same to float rounding)
        gain = scale * (var + self.eps).rsqrt()
        return torch.addcmul(bias - mean * gain, x, gain)

    def _training_statistics(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The mean and variance to normalize ``x`` with in training: the batch's during the
        warm-up, then the running ones corrected towards the batch's (a gradient flows through
        the batch statistics, not through the correction). Moves the running statistics."""
        batch_mean = x.mean(dim=1, keepdim=True)
        # unbiased, as sb3-contrib; the centred squares summed rather than torch.var, whose
        # reduction over the middle (batch) dim is strided: half the time on a CPU, the same
        # variance to float rounding (about 1e-7 relative)
        centred = x - batch_mean
        batch_var = (centred * centred).sum(dim=1, keepdim=True) / (x.shape[1] - 1)
        running_std = (self.running_var + self.eps).sqrt()
        with torch.no_grad():
            r = ((batch_var + self.eps).sqrt() / running_std).clamp(1 / self.R_MAX, self.R_MAX)
            d = ((batch_mean - self.running_mean) / running_std).clamp(-self.D_MAX, self.D_MAX)
        # a device-side choice of branch: no host sync on the step counter. The branch not taken
        # still gets a zero gradient: its variance is 1 then, so sqrt's gradient at a constant
        # feature's zero variance (0 * inf = NaN) never reaches the weights
        past_warmup = (self.steps > self.warmup_steps).view(-1, 1, 1)
        var_if_past = torch.where(past_warmup, batch_var, torch.ones_like(batch_var))
        renorm_mean = batch_mean - d * var_if_past.sqrt() / r
        renorm_var = var_if_past / r.pow(2)
        mean = torch.where(past_warmup, renorm_mean, batch_mean)
        var = torch.where(past_warmup, renorm_var, batch_var)
        with torch.no_grad():
            self.running_mean.lerp_(batch_mean, self.momentum)
            self.running_var.lerp_(batch_var, self.momentum)
            self.steps += 1
        return mean, var


@contextmanager
def batch_statistics(network: nn.Module) -> Iterator[None]:
    """Inside, every renormalization of ``network`` normalizes with its batch's statistics and
    moves its running statistics (training mode); outside, it uses the running ones."""
    renorms = [m for m in network.modules() if isinstance(m, EnsembleBatchRenorm)]
    for module in renorms:
        module.train(True)
    try:
        yield
    finally:
        for module in renorms:
            module.train(False)


class RenormCriticEnsemble(nn.Module):
    """``n`` Q-networks with Batch Renormalization before every linear layer (CrossQ's critic):
    Q_i(s, a) = Linear(BRN(ReLU(Linear(BRN(... BRN([s, a])))))) -> ``(n, batch)``."""

    def __init__(self, obs_dim, act_dim, hidden_sizes: Sequence[int], n: int, **renorm):
        super().__init__()
        dims = [obs_dim + act_dim, *hidden_sizes, 1]
        self.norms = nn.ModuleList(EnsembleBatchRenorm(n, d, **renorm) for d in dims[:-1])
        self.layers = nn.ModuleList(
            EnsembleLinear(n, a, b) for a, b in zip(dims[:-1], dims[1:], strict=True)
        )
        self.eval()  # running statistics unless a pass asks for batch statistics

    def forward(self, obs, action, members: slice = slice(None)) -> torch.Tensor:
        x = torch.cat([obs, action], dim=-1)
        for norm, layer in zip(self.norms[:-1], self.layers[:-1], strict=True):
            x = F.relu(layer(norm(x, members), members))
        return self.layers[-1](self.norms[-1](x, members), members).squeeze(-1)


class RenormGaussianActor(EnsembleGaussianActor):
    """SAC's squashed Gaussian actor with Batch Renormalization before each linear layer and
    before the head (CrossQ's actor, as sb3-contrib builds it). Built like its parent, with the
    renormalization's ``momentum`` and ``warmup_steps``."""

    def __init__(self, n, obs_dim, act_dim, hidden_sizes, action_low, action_high, **renorm):
        super().__init__(n, obs_dim, act_dim, hidden_sizes, action_low, action_high)
        widths = [obs_dim, *hidden_sizes]
        self.norms = nn.ModuleList(EnsembleBatchRenorm(n, d, **renorm) for d in widths)
        self.eval()

    def distribution(
        self, obs: torch.Tensor, members: slice = slice(None)
    ) -> tuple[torch.Tensor, torch.Tensor]:
        x = obs
        for norm, layer in zip(self.norms[:-1], self.layers[:-1], strict=True):
            x = F.relu(layer(norm(x, members), members))
        mean, log_std = self.layers[-1](self.norms[-1](x, members), members).chunk(2, dim=-1)
        return mean, log_std.clamp(self.LOG_STD_MIN, self.LOG_STD_MAX)
