"""The NaN/inf guard every agent shares: skipped updates, counted on the device.

An optimizer step whose loss or gradient is not finite is skipped and the update counted. Every
agent calls the guard where it takes the step, between ``backward()`` and ``step()``:
:func:`skip_nonfinite` (per-member losses: a population's members, each skipped on its own) or
:func:`clip_or_skip` (one agent's scalar loss, with gradient clipping). They set the fused
optimizer's ``found_inf``, which makes its step a no-op, here and nowhere else; an update
compiled on the CPU skips the same members (:func:`skipped_members`) in its own Adam step
(:func:`walkers.agents.common.functional.guarded_adam_step`).
Checks and counts are device tensors, so the guard adds no host-device sync to the hot loop; the
trainer reads ``health/*`` only when it logs, and ends a run whose updates have all been skipped
for too long (:class:`walkers.training.bookkeeping.TrainingDiverged`).
"""

from __future__ import annotations

import torch

SKIPPED = "health/skipped_updates"
SKIPPED_IN_A_ROW = "health/skipped_in_a_row"


class NonFiniteGuard:
    """Counters of shape ``shape``: ``()`` for one agent, ``(K,)`` for a population of K."""

    def __init__(self, device: torch.device, shape: tuple[int, ...] = ()):
        self.skipped = torch.zeros(shape, device=device)
        self.in_a_row = torch.zeros(shape, device=device)
        #: a delayed step (TD3's actor, every d updates) that was skipped the last time it ran:
        #: the updates in between, which do not run it, are no proof that it recovered
        self.delayed_bad = torch.zeros(shape, device=device)

    @staticmethod
    def bad_members(*values: torch.Tensor) -> torch.Tensor:
        """Per member (the first dimension of each value): 1.0 where any is NaN/inf."""
        finite = torch.isfinite(values[0])
        for value in values[1:]:
            finite &= torch.isfinite(value)
        return (~finite).to(torch.float32)

    def record(self, bad: torch.Tensor, delayed_bad: torch.Tensor | None = None) -> None:
        """Count one update: ``bad`` where its steps were skipped; ``delayed_bad`` where it ran
        the delayed step, whether that step was skipped (it counts until the step runs again)."""
        # in place: a captured update's graphs all read and write these same counters
        if delayed_bad is not None:
            self.delayed_bad.copy_(delayed_bad)
        bad = torch.maximum(bad, self.delayed_bad)
        self.skipped += bad
        self.in_a_row.add_(bad).mul_(bad)  # (in_a_row + bad) * bad: reset by any good update

    def metrics(self) -> dict[str, torch.Tensor]:
        """This update's counts (copies: the counters themselves change in place)."""
        return {SKIPPED: self.skipped.clone(), SKIPPED_IN_A_ROW: self.in_a_row.clone()}

    _COUNTERS = ("skipped", "in_a_row", "delayed_bad")

    def state_dict(self) -> dict:
        return {name: getattr(self, name).tolist() for name in self._COUNTERS}

    def member_state_dict(self, i: int) -> dict:
        """Member ``i``'s counters, as a population of one's :meth:`state_dict`."""
        return {name: [getattr(self, name)[i].item()] for name in self._COUNTERS}

    def load_member_state_dict(self, i: int, state: dict) -> None:
        for name in self._COUNTERS:  # checkpoints from before delayed_bad: none was bad
            (getattr(self, name)[i],) = state.get(name, [0.0])

    def load_state_dict(self, state: dict) -> None:
        for name in self._COUNTERS:
            counter = getattr(self, name)
            counter.copy_(torch.as_tensor(state.get(name, torch.zeros_like(counter).tolist())))


def skip_nonfinite(
    optimizer: torch.optim.Optimizer,
    member_loss: torch.Tensor,
    copies: int = 1,
    also_skip: torch.Tensor | None = None,
) -> torch.Tensor:
    """Between ``backward`` and ``step``: skip the members whose loss or gradient is NaN/inf (a
    finite loss can still have an infinite gradient), for per-member losses ``(K,)``.

    No host sync: a bad member's gradients are zeroed (NaN included), and fused Adam's
    ``found_inf`` skips the whole step when every member is bad (for a single agent: whenever
    it is). ``copies``: parameter members per agent member (e.g. the critics per member);
    ``also_skip``: members to skip for another reason. ``optimizer``: fused (Adam, AdamW), the
    kind that reads ``found_inf``. Returns the skipped members ``(K,)`` (1.0 skipped, 0.0 taken).
    """
    grads = _gradients(optimizer)
    bad = skipped_members(grads, member_loss, also_skip)
    optimizer.found_inf = bad.min()  # the fused step is a no-op when every member is bad
    # one agent: found_inf skips the step already; on a CPU, reading ``bad`` costs no sync, and
    # a population whose members are all good (nearly every update) has nothing to zero
    if member_loss.numel() > 1 and (grads[0].device.type != "cpu" or bool(bad.any())):
        skip = (bad > 0).repeat_interleave(copies)
        for grad in grads:  # members lead every parameter's dimensions
            grad.masked_fill_(skip.view(-1, *(1,) * (grad.dim() - 1)), 0.0)
    return bad.view(member_loss.shape)


def clip_or_skip(
    optimizer: torch.optim.Optimizer, loss: torch.Tensor, max_grad_norm: float | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Between ``backward`` and ``step`` of one agent's scalar ``loss``: the global gradient
    norm clipped to ``max_grad_norm`` (None: no clip), and the step skipped (``found_inf``)
    where the loss or that norm is NaN/inf. Returns ``(skipped, grad_norm)``: 1.0 where the step
    was skipped (shaped like the loss), and the norm before clipping, for logging."""
    params = [p for group in optimizer.param_groups for p in group["params"]]
    grad_norm = torch.nn.utils.get_total_norm(_gradients(optimizer))
    if max_grad_norm is not None:  # what clip_grad_norm_ does, reusing the norm
        torch.nn.utils.clip_grads_with_norm_(params, max_grad_norm, grad_norm)
    bad = torch.maximum(NonFiniteGuard.bad_members(loss.view(-1)), _not_finite(grad_norm).view(1))
    optimizer.found_inf = bad.min()  # the fused step is a no-op when the agent is bad
    return bad.view(loss.shape), grad_norm


def skipped_members(
    grads: list[torch.Tensor], member_loss: torch.Tensor, also_skip: torch.Tensor | None = None
) -> torch.Tensor:
    """The members ``(K,)`` to skip (1.0) for per-member losses ``(K,)`` and their gradients:
    a NaN/inf loss or gradient, or ``also_skip``. One agent: the total norm (fused over all
    gradients) is finite or not; a population: each member's gradient sums."""
    members = member_loss.numel()
    if members == 1:
        bad_grads = _not_finite(torch.nn.utils.get_total_norm(grads)).view(1)
    else:
        bad_grads = _bad_member_gradients(grads, members)
    bad = torch.maximum(NonFiniteGuard.bad_members(member_loss.view(-1)), bad_grads)
    if also_skip is not None:
        bad = torch.maximum(bad, also_skip)
    return bad


def _gradients(optimizer: torch.optim.Optimizer) -> list[torch.Tensor]:
    return [
        p.grad for group in optimizer.param_groups for p in group["params"] if p.grad is not None
    ]


def _not_finite(x: torch.Tensor) -> torch.Tensor:
    return (~torch.isfinite(x)).to(torch.float32)


def _bad_member_gradients(grads: list[torch.Tensor], members: int) -> torch.Tensor:
    """Per member ``(members,)``: 1.0 where any of its gradients is NaN/inf. Every parameter's
    leading dimension holds the members (each member's copies, e.g. its critics, together).

    One pass over the gradients: a member's sum is NaN/inf where any of its entries is (inf
    plus -inf is NaN), and finite gradients whose sum overflows float32 are no step to take."""
    sums = torch.stack([grad.reshape(members, -1).sum(dim=1) for grad in grads])
    return _not_finite(sums.sum(dim=0))
