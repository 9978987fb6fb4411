"""An off-policy agent's checkpoints: a single agent's is member 0 cut out, a population's its
members' (:mod:`walkers.agents.common.population` cuts and loads them), with the counters, and a
buffer lost on resume refilled before updating again."""

from __future__ import annotations

from walkers.agents.common import population as members_io


class MemberCheckpoints:
    """The checkpoint half of :class:`~walkers.agents.common.actor_critic.ActorCritic`: its
    ``population`` members, their parts (:meth:`member_cuts`), the replay counters and the
    refill a resume without the buffer's transitions needs."""

    # --- checkpoints: a single agent's is member 0 cut out, a population's its members' --------
    def state_dict(self, with_buffer: bool = False) -> dict:
        if self.population == 1:
            return members_io.member_state_dict(self, 0, with_buffer)
        return {
            "members": [
                members_io.member_state_dict(self, i, with_buffer) for i in range(self.population)
            ]
        }

    def load_state_dict(self, state: dict) -> None:
        for i, member_state in enumerate(state.get("members", [state])):
            members_io.load_member_state_dict(self, i, member_state)

    def load_counters(self, state: dict) -> None:
        self.steps, self.num_updates = state["steps"], state["num_updates"]
        self.random_until = state.get("random_until", self.learning_starts)
        self.update_after = state.get("update_after", self.learning_starts)

    def refill_if_lost(self, buffer_state: dict) -> None:
        """A checkpoint without its transitions: refill the buffer before updating again.

        Updating at once would fit the critics to the few transitions collected since (silently
        a different experiment). Instead the agent collects ``max(learning_starts, batch_size)``
        transitions first: of the current policy with exploration noise, or uniform random ones
        if the run was interrupted in its warm-up (the warm-up restarts whole). Silent here: an
        agent restored only to act (walkers.evaluate, walkers.collect) never refills.
        """
        if "data" in buffer_state or buffer_state.get("size", 0) == 0:
            return
        refill = max(self.learning_starts, self.batch_size)
        in_warmup = self.steps < self.random_until
        if in_warmup:
            self.random_until = self.steps + refill
        self.update_after = max(self.update_after, self.steps + refill)
        self.refilled_at = self.steps  # the trainer says so when it resumes (resume_notes)
        self.refill_kind = (
            "uniform random: the warm-up again" if in_warmup else "current policy with noise"
        )

    def resume_notes(self) -> dict[str, str]:
        if self.refilled_at is None:
            return {}
        return {
            "walkers.buffer_refill": f"steps {self.refilled_at}-{self.update_after} "
            f"({self.refill_kind})"
        }

    # --- a population's members one at a time (walkers.agents.common.population) ---------------
    def member_cuts(self, i: int) -> dict[str, slice]:
        """Member ``i``'s slice of the leading dimension of every per-member part, by attribute
        name: modules (their state dicts) and optimizers (their Adam moments). A member's
        checkpoint holds these parts, cut; an algorithm with more parts (targets, a temperature)
        adds them."""
        own, critics = self.own_slice(i), self.critics_slice(i)
        return {
            "actor": own,
            "critic": critics,
            "actor_optimizer": own,
            "critic_optimizer": critics,
        }

    @staticmethod
    def own_slice(i: int) -> slice:
        """Member ``i``'s entry of a per-member part (the actor, a temperature)."""
        return slice(i, i + 1)

    def critics_slice(self, i: int) -> slice:
        """Member ``i``'s critics in the critic ensemble."""
        return slice(i * self.num_critics, (i + 1) * self.num_critics)

    def member_policy(self, i: int) -> members_io.MemberAgent:
        """Member ``i`` as an agent of its own (evaluation rollouts, its checkpoints)."""
        return members_io.MemberAgent(self, i)

    def member_state_dict(self, i: int, with_buffer: bool = False) -> dict:
        return members_io.member_state_dict(self, i, with_buffer)

    def load_member_state_dict(self, i: int, state: dict) -> None:
        members_io.load_member_state_dict(self, i, state)
