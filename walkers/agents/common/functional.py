"""``algo.compile=true`` on the CPU: an update's gradient steps as functions of tensors, so that
``torch.compile`` takes the whole update as one program.

On a CPU core most of an eager update that is not matrix products is per-op dispatch, the
autograd tape and small memory-bound ops (ReLU and its backward, bias copies, Adam, the guard):
about 40% of TD3's update on a 256-256 network (``make bench``). ``torch.compile`` of the losses
alone leaves the backward passes, the optimizer steps and the guard outside its graphs and runs
slower than eager there. Compiling the update as written breaks on ``backward()``, on the
frozen critic of the actor's loss and on fused Adam, each a graph break. Written with
:func:`torch.func.grad` instead of ``backward()``, and with Adam and the NaN guard as tensor ops,
an update is one graph per way through it (TD3: with and without the delayed step), which
Inductor fuses into a few loops.

The pieces keep the eager update's state and meaning: the gradients are of the algorithm's own
loss methods (:func:`gradient_of`), the Adam moments and step counts are the optimizer's
own ``state`` tensors (checkpoints are the same), and :func:`guarded_adam_step` skips exactly
what :func:`~walkers.agents.common.health.skip_nonfinite` and fused Adam's ``found_inf`` skip.
The numbers are the eager update's to float32 rounding, not bit for bit: Inductor sums in other
orders, so a compiled run is an arm of its own (docs/speed.md).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from walkers.agents.common.health import skipped_members

#: The per-parameter moments of Adam's state (a member's checkpoint holds its slice of each).
ADAM_MOMENTS = ("exp_avg", "exp_avg_sq")


class _Loss(nn.Module):
    """A loss method as the forward of a module holding ``network``, for functional_call."""

    def __init__(self, network: nn.Module, loss: Callable[..., tuple]):
        super().__init__()
        self.network, self.loss = network, loss

    def forward(self, *args) -> tuple:
        return self.loss(*args)


def gradient_of(
    network: nn.Module, loss: Callable[..., tuple]
) -> Callable[..., tuple[list[torch.Tensor], tuple]]:
    """The gradient of an algorithm's loss method with respect to one network's parameters:
    ``gradient_of(network, loss)(*args)`` is ``(gradients, loss(*args))``, the gradients in the
    order of ``network.parameters()``, of the sum of the per-member loss ``loss(*args)[0]``
    (members' losses are independent, so each member's gradient is its own). The loss method
    reads the network as it always does: :func:`torch.func.functional_call` swaps its
    parameters for the call. Every other tensor the loss reads is a constant, as a frozen
    network is to ``backward()``. Built once, outside the compiled update."""
    module = _Loss(network, loss)

    def gradient(*args) -> tuple[list[torch.Tensor], tuple]:
        def summed(params):
            out = torch.func.functional_call(module, params, args)
            return out[0].sum(), out

        params = {f"network.{name}": p.detach() for name, p in network.named_parameters()}
        grads, out = torch.func.grad(summed, has_aux=True)(params)
        return list(grads.values()), out

    return gradient


def adam_state(optimizer: torch.optim.Optimizer) -> list[tuple[torch.Tensor, dict]]:
    """Each parameter of ``optimizer`` with its Adam state, created as its first step would
    (``step`` a float32 scalar, zero moments): the state fused Adam reads and checkpoints hold."""
    pairs = []
    for group in optimizer.param_groups:
        for p in group["params"]:
            state = optimizer.state[p]
            if not state:
                state["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
                state |= {key: torch.zeros_like(p) for key in ADAM_MOMENTS}
            pairs.append((p, state))
    return pairs


@torch.no_grad()
def guarded_adam_step(
    optimizer: torch.optim.Optimizer,
    grads: list[torch.Tensor],
    member_loss: torch.Tensor,
    copies: int = 1,
    also_skip: torch.Tensor | None = None,
) -> torch.Tensor:
    """:func:`~walkers.agents.common.health.skip_nonfinite` and ``optimizer.step()`` in tensor
    ops: a member whose loss or gradient is NaN/inf (or in ``also_skip``) has its gradients
    zeroed, and the step (moments, step count, weights) is not taken when every member is bad.
    Adam as in Kingma and Ba (2015), Algorithm 1, with the optimizer's ``lr``, ``betas`` and
    ``eps``. Returns the skipped members ``(K,)`` (1.0 skipped)."""
    bad = skipped_members(grads, member_loss, also_skip)  # as skip_nonfinite's
    skip = (bad > 0).repeat_interleave(copies)
    take = bad.min() == 0  # found_inf: no step at all when every member is bad
    group = optimizer.param_groups[0]
    lr, (beta1, beta2), eps = group["lr"], group["betas"], group["eps"]
    for (p, state), grad in zip(adam_state(optimizer), grads, strict=True):
        grad = grad.masked_fill(skip.view(-1, *(1,) * (grad.dim() - 1)), 0.0)
        step = state["step"] + 1
        exp_avg = state["exp_avg"].lerp(grad, 1 - beta1)
        exp_avg_sq = state["exp_avg_sq"] * beta2 + (1 - beta2) * grad * grad
        bias_correction1 = 1 - beta1**step
        bias_correction2_sqrt = (1 - beta2**step).sqrt()
        denom = exp_avg_sq.sqrt() / bias_correction2_sqrt + eps
        new_p = p - (lr / bias_correction1) * exp_avg / denom
        p.copy_(torch.where(take, new_p, p))
        state["exp_avg"].copy_(torch.where(take, exp_avg, state["exp_avg"]))
        state["exp_avg_sq"].copy_(torch.where(take, exp_avg_sq, state["exp_avg_sq"]))
        state["step"].copy_(torch.where(take, step, state["step"]))
    return bad.view(member_loss.shape)
