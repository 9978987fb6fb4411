"""On-policy rollouts: the steps an agent collected with its current policy, and their returns.

REINFORCE and PPO keep what they act on in a :class:`Rollout`, one step at a time in the order
the trainer feeds them, episode boundaries included, and compute their learning targets here:

- REINFORCE takes whole episodes (:meth:`Rollout.pop_episodes`) and their Monte-Carlo
  returns-to-go (:func:`returns_to_go`: no value function, nothing to bootstrap from);
- PPO takes a fixed number of steps (:meth:`Rollout.take`) that may start and end mid-episode and
  computes GAE(lambda) advantages (:func:`gae`), bootstrapping from V(s') where an episode was cut
  by a time limit or the rollout ends. A terminal state (``terminated``) is never bootstrapped.
"""

from __future__ import annotations

import numpy as np


class Rollout:
    """Steps in collection order: named per-step fields (stored as float32) plus episode ends.

    ``add(episode_end, **fields)`` appends one step; every step carries the same fields.
    """

    def __init__(self):
        self._fields: dict[str, list] = {}
        self._ends: list[bool] = []
        self._episodes = 0  # complete episodes held (kept, not counted: asked every step)

    def __len__(self) -> int:
        return len(self._ends)

    def add(self, episode_end: bool, **fields) -> None:
        for name, value in fields.items():  # a copy: an env may reuse its observation buffer
            self._fields.setdefault(name, []).append(np.array(value, dtype=np.float32))
        self._ends.append(bool(episode_end))
        self._episodes += bool(episode_end)

    @property
    def num_episodes(self) -> int:
        """Complete episodes held (an unfinished one at the end is not counted)."""
        return self._episodes

    def cut(self) -> None:
        """End the episode at the last step (a resumed run starts a new one there: for a learner
        that bootstraps, the cut is a truncation, never a terminal state)."""
        if self._ends and not self._ends[-1]:
            self._ends[-1] = True
            self._episodes += 1

    def take(self) -> dict[str, np.ndarray]:
        """Every step, stacked (``episode_end``: bool), leaving the rollout empty."""
        data = self._stacked(len(self))
        self._fields, self._ends, self._episodes = {}, [], 0
        return data

    def pop_episodes(self) -> list[dict[str, np.ndarray]]:
        """The complete episodes, each its fields stacked; an unfinished tail stays."""
        if not self.num_episodes:
            return []
        done = len(self._ends) - self._ends[::-1].index(True)  # steps up to the last episode end
        data = self._stacked(done)
        self._fields = {name: values[done:] for name, values in self._fields.items()}
        self._ends, self._episodes = self._ends[done:], 0
        bounds = np.flatnonzero(data.pop("episode_end")) + 1
        return [
            {name: values[start:stop] for name, values in data.items()}
            for start, stop in zip(np.r_[0, bounds[:-1]], bounds, strict=True)
        ]

    def _stacked(self, n: int) -> dict[str, np.ndarray]:
        data = {name: np.stack(values[:n]) for name, values in self._fields.items()}
        data["episode_end"] = np.asarray(self._ends[:n], dtype=bool)
        return data

    # --- checkpoints --------------------------------------------------------------------------
    def state_dict(self) -> dict[str, np.ndarray]:
        return self._stacked(len(self)) if len(self) else {}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        state = dict(state)
        ends = state.pop("episode_end", np.zeros(0, dtype=bool))
        self._fields = {name: list(values) for name, values in state.items()}
        self._ends = [bool(e) for e in ends]
        self._episodes = sum(self._ends)


def returns_to_go(rewards: np.ndarray, gamma: float) -> np.ndarray:
    """G_t = r_t + gamma * G_{t+1}, computed backwards over one episode."""
    out = np.zeros_like(rewards, dtype=np.float32)
    running = 0.0
    for t in range(len(rewards) - 1, -1, -1):
        running = rewards[t] + gamma * running
        out[t] = running
    return out


def gae(
    rewards: np.ndarray,
    values: np.ndarray,
    next_values: np.ndarray,
    terminated: np.ndarray,
    episode_end: np.ndarray,
    gamma: float,
    lam: float,
) -> tuple[np.ndarray, np.ndarray]:
    """GAE(lambda) advantages and value targets of a rollout of T steps (Schulman et al. 2016).

        delta_t = r_t + gamma * (1 - terminated_t) * V(s'_t) - V(s_t)
        A_t     = delta_t + gamma * lam * (1 - episode_end_t) * A_{t+1}       (A_T = 0)

    ``next_values[t]`` is V(s'_t), the value of step t's own next state: ``values[t + 1]`` inside
    an episode; at a time-limit truncation (``episode_end`` and not ``terminated``) and at the
    rollout's last step, the value of that step's next observation, which is bootstrapped; after a
    terminal step it is ignored. The trace stops at every episode end. Returns ``(A, A + V)``: the
    advantages and the lambda-returns the value function regresses on. All float32, shape (T,).
    """
    r, v, nv = (np.asarray(x, np.float64).tolist() for x in (rewards, values, next_values))
    term = np.asarray(terminated, bool).tolist()
    ends = np.asarray(episode_end, bool).tolist()
    advantages = [0.0] * len(r)
    running = 0.0
    for t in range(len(r) - 1, -1, -1):
        bootstrap = 0.0 if term[t] else gamma * nv[t]
        delta = r[t] + bootstrap - v[t]
        running = delta + (0.0 if ends[t] else gamma * lam * running)
        advantages[t] = running
    advantages = np.asarray(advantages, dtype=np.float64)
    return advantages.astype(np.float32), (advantages + v).astype(np.float32)
