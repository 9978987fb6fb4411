"""Off-policy actor-critic with experience replay: what TD3, DDPG, SAC, CrossQ and TD7 share.

Each algorithm owns its update, written in its paper's order in its own module:

- :mod:`walkers.agents.td3`: TD3 (Fujimoto et al. 2018, Algorithm 1); :mod:`walkers.agents.ddpg`
  is TD3 with its three ideas off;
- :mod:`walkers.agents.sac`: SAC v2 (Haarnoja et al. 2018, Algorithm 1);
- :mod:`walkers.agents.crossq`: CrossQ (Bhatt et al. 2024): SAC without target networks, with
  Batch Renormalization in wide critics and one joint forward pass;
- :mod:`walkers.agents.td7`: TD7 (Fujimoto et al. 2023): TD3 with SALE embeddings, LAP
  prioritised replay (its own :attr:`~ActorCritic.replay_class`), hard target updates and value
  clipping.

This core holds only what they share, none of it particular to one algorithm: the actor and
critic ensembles and their Adam optimizers, the replay buffers and the uniform random warm-up,
acting, one mini-batch per member (:meth:`ActorCritic.sample`), the NaN/inf guard's counters
(each step calls the guard itself, :func:`~walkers.agents.common.health.skip_nonfinite`), target
networks for those that have them (:meth:`target_of`,
:func:`~walkers.agents.common.networks.soft_update`), ``compile``, populations and checkpoints.
The core builds nothing by itself: each algorithm's constructor builds its networks, optimizers
and members explicitly, after setting itself up.

Every network is an ensemble with a leading *member* dimension: a single agent is a population of
one, ``population=K`` trains K independent seeds (``seed, seed + 1, ...``) with one batched
matmul a layer for all of them. Each member has its own replay buffer, exploration noise and RNG
(:class:`Member`); losses are sums of per-member losses, so each member's gradient is its own,
and Adam, being elementwise, keeps members independent under one optimizer. Cutting a member out
as a single agent and loading it back is :meth:`ActorCritic.member_state_dict` and
:meth:`ActorCritic.load_member_state_dict`.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from walkers.agents.base import (
    Agent,
    Policy,
    Transition,
    autocast,
    resolve_device,
    warn_if_slow_precision,
)
from walkers.agents.common.capture import CapturedUpdate
from walkers.agents.common.functional import ADAM_MOMENTS, adam_state
from walkers.agents.common.health import NonFiniteGuard
from walkers.agents.common.networks import EnsembleActor, make_critic
from walkers.data.replay import Batch, ReplayBuffer
from walkers.seeding import RandomStreams, numpy_rng

log = logging.getLogger("walkers")


class ActorCritic(Agent):
    """The shared core (see the module docstring). An algorithm subclasses it: its constructor
    calls this one (settings and counters only: nothing is built yet), sets up its own
    attributes, then builds its parts explicitly with :meth:`build_actor`, :meth:`build_critic`,
    :meth:`target_of`, :meth:`adam` and :meth:`build_members`, in that order (the order of the
    seeded initialisations), and last :meth:`compile_update`. It writes its own :meth:`update`
    and :meth:`policy`, and lists its per-member parts beyond the core's (:meth:`member_cuts`:
    what a member's checkpoint holds)."""

    num_critics = 2  # critics per member
    trains_populations = True  # population=K: K seeds, one batched matmul a layer
    #: the methods ``compile=True`` runs through torch.compile (the losses, forward and backward)
    compiled_losses: tuple[str, ...] = ("critic_loss", "actor_loss")
    #: the method ``capture`` holds as CUDA graphs: the whole :meth:`update`, or the part of it
    #: whose ways through repeat with :attr:`update_period` (TD7's hard target copies every 250
    #: updates stay outside its graphs)
    captured_step = "update"
    #: the replay buffer's class (TD7's prioritises its transitions)
    replay_class: type[ReplayBuffer] = ReplayBuffer

    def __init__(
        self,
        obs_dim: int,
        action_low: Sequence[float],
        action_high: Sequence[float],
        *,
        lr: float,
        batch_size: int,
        learning_starts: int,
        hidden_sizes: Sequence[int],
        gamma: float,
        tau: float | None = None,  # soft updates of target networks (CrossQ has none)
        buffer_size: int,
        actor_lr: float | None = None,
        critic_lr: float | None = None,
        critic_architecture: str | None = None,
        critic_hidden_sizes: Sequence[int] | None = None,
        adam_betas: Sequence[float] | None = None,  # None: Adam's own (0.9, 0.999)
        population: int = 1,
        compile: bool,
        capture: bool | str,
        precision: str | None = None,  # CrossQ and TD7 declare none: fp32
        device: str = "cpu",
        seed: int = 0,
    ):
        self.device = resolve_device(device)
        self.precision = precision or "fp32"
        warn_if_slow_precision(self.device, self.precision)
        self.batch_size, self.learning_starts = int(batch_size), int(learning_starts)
        self.gamma, self.tau = gamma, tau
        self.population, self.seed = int(population), seed
        self.obs_dim = obs_dim
        self.action_low = np.asarray(action_low, dtype=np.float32)
        self.action_high = np.asarray(action_high, dtype=np.float32)
        self.act_dim = len(self.action_low)
        self._uniform_low = self.action_low.astype(np.float64)  # uniform_actions' bounds
        self._uniform_range = self.action_high.astype(np.float64) - self._uniform_low
        self.low_t = torch.as_tensor(self.action_low, device=self.device)
        self.high_t = torch.as_tensor(self.action_high, device=self.device)
        self.hidden_sizes = list(hidden_sizes)
        self.critic_hidden_sizes = list(critic_hidden_sizes or hidden_sizes)
        # TD3's and SAC's critic architecture is "mlp"; DDPG declares the choice
        self.critic_architecture = critic_architecture or "mlp"
        self.actor_lr, self.critic_lr = actor_lr or lr, critic_lr or lr
        self.adam_betas = (0.9, 0.999) if adam_betas is None else tuple(adam_betas)
        self.buffer_size, self.compile = int(buffer_size), compile
        # the whole update as CUDA graphs: on CUDA only (the CPU keeps the eager update); "auto"
        # captures where it can, leaving the update to torch.compile when that is asked for
        wanted = capture is True or (capture == "auto" and not compile)
        self.capture = wanted and self.device.type == "cuda"
        if capture is True and not self.capture:
            log.warning("algo.capture=true needs CUDA: on %s the update runs eagerly", self.device)

        self.member_seeds = list(range(seed, seed + self.population))
        # The networks the subclass builds next draw from torch's RNG seeded here; in a
        # population each member's part draws from its own seed's (_per_member).
        self._init_rng_states = []
        for member_seed in self.member_seeds:
            torch.manual_seed(member_seed)
            self._init_rng_states.append(torch.get_rng_state())
        torch.manual_seed(seed)
        self.steps = 0  # transitions observed (per member)
        self.num_updates = 0  # critic updates done
        # Uniform random actions while steps < random_until, no updates while steps < update_after:
        # both learning_starts, unless a run resumed without its replay buffer refills it.
        self.random_until = self.update_after = self.learning_starts
        self.refilled_at: int | None = None  # the step a resume without the buffer refilled from
        self.guard = NonFiniteGuard(self.device, (self.population,))

    # --- construction: called by the algorithm's constructor, in this order ----------------------
    def build_actor(self, actor_class: type[nn.Module] = EnsembleActor, **options) -> nn.Module:
        """The actors of every member, one ensemble of ``population``: ``actor_class(n, obs_dim,
        act_dim, hidden_sizes, action_low, action_high, **options)``."""

        def actors(n: int) -> nn.Module:
            return actor_class(
                n,
                self.obs_dim,
                self.act_dim,
                self.hidden_sizes,
                self.action_low,
                self.action_high,
                **options,
            ).to(self.device)

        return self._per_member(actors, 1)

    def build_critic(self, critic_class: type[nn.Module] | None = None, **options) -> nn.Module:
        """The critics of every member as one ensemble of ``num_critics * population``:
        ``critic_class(obs_dim, act_dim, critic_hidden_sizes, n, **options)``, by default the
        declared ``critic_architecture``."""

        def critics(n: int) -> nn.Module:
            if critic_class is None:
                return make_critic(
                    self.critic_architecture,
                    self.obs_dim,
                    self.act_dim,
                    self.critic_hidden_sizes,
                    n,
                ).to(self.device)
            return critic_class(
                self.obs_dim, self.act_dim, self.critic_hidden_sizes, n, **options
            ).to(self.device)

        return self._per_member(critics, self.num_critics)

    def _per_member(self, build: Callable[[int], nn.Module], per_member: int) -> nn.Module:
        """``build(per_member * population)``, each member's slice initialised as a single run
        of its seed initialises its own (``build(per_member)`` from torch's RNG as that run's
        would stand), so that member k starts where a single run of seed k starts."""
        network = build(per_member * self.population)
        if self.population == 1:
            return network
        for k, rng_state in enumerate(self._init_rng_states):
            torch.set_rng_state(rng_state)
            own = build(per_member).state_dict()
            self._init_rng_states[k] = torch.get_rng_state()
            cut = slice(k * per_member, (k + 1) * per_member)
            with torch.no_grad():
                for name, value in network.state_dict().items():
                    value[cut] = own[name]
        return network

    @staticmethod
    def target_of(network: nn.Module) -> nn.Module:
        """A target network theta' of ``network``: a frozen copy, moved by soft updates."""
        return copy.deepcopy(network).requires_grad_(False)

    def adam(self, module: nn.Module, lr: float, betas: Sequence[float] | None = None):
        """Fused Adam on ``module``'s parameters (fused: one kernel, and ``found_inf`` for the
        NaN guard; capturable in a CUDA graph when the update is captured); ``betas``: the
        declared ``adam_betas`` unless given."""
        betas = self.adam_betas if betas is None else tuple(betas)
        return torch.optim.Adam(
            module.parameters(), lr=lr, betas=betas, fused=True, capturable=self.capture
        )

    def build_members(
        self, exploration_noise: Callable[[np.random.Generator], GaussianNoise]
    ) -> list[Member]:
        """Each member's own parts: its exploration stream and its noise process drawing from
        that stream (``exploration_noise(rng)``). With them come the parts the members hold as
        one: the replay buffer (:attr:`buffer`, each member's transitions and sampling stream) and
        the update's noise streams (:meth:`noise_like`), keyed by the members' seeds."""
        self.buffer = self.replay_class(
            self.buffer_size, self.obs_dim, self.act_dim, self.device, self.member_seeds
        )
        self.update_noise = RandomStreams.of_seeds(self.member_seeds, "update_noise", self.device)
        members = []
        for member_seed in self.member_seeds:
            rng = numpy_rng(member_seed, "exploration")
            members.append(Member(rng, exploration_noise(rng)))
        return members

    def compile_update(self) -> None:
        """``capture=True`` on CUDA: the whole :meth:`update` as CUDA graphs
        (:class:`~walkers.agents.common.capture.CapturedUpdate`). ``compile=True`` on the CPU,
        where the algorithm writes its steps functionally (:meth:`functional_gradients`): those
        steps, whole, through ``torch.compile`` (:mod:`walkers.agents.common.functional`);
        otherwise the loss computations (:attr:`compiled_losses`), forward and backward, on
        CUDA with CUDA graphs (``reduce-overhead``), where a small update is launch-bound. The
        optimizer steps stay eager there: fused Adam is one kernel already and keeps the NaN
        guard's step skip."""
        self.compiled_steps = None
        if self.precision != "fp32":  # the whole update under autocast, as capture and compile
            update = self.update  # take it (they trace it inside the autocast)

            def update_in_precision() -> dict[str, torch.Tensor]:
                with autocast(self.device, self.precision):
                    return update()

            self.update = update_in_precision
        if self.capture:
            step = self.captured_step
            setattr(self, step, CapturedUpdate(self, getattr(self, step)))
        if not self.compile:
            return
        gradients = self.functional_gradients() if self.device.type == "cpu" else None
        if gradients:
            vars(self).update(gradients)
            for part in list(vars(self).values()):
                if isinstance(part, torch.optim.Optimizer):
                    adam_state(part)  # made now: the compiled steps update it in place
            # Dynamo compiles anew for each agent (its guards hold the agent's objects) and
            # stops compiling a function after 8, which a process that trains agent after agent
            # (a multirun's jobs in turn) would reach: each compiled agent starts from empty
            # caches (one agent trains at a time).
            torch.compiler.reset()
            compiled = torch.compile(self.functional_steps, fullgraph=True)

            def first(*draws):  # said when it happens (an agent that only acts never compiles)
                log.info("compile=true: compiling the update (20-30 s on a CPU, once a process)")
                self.compiled_steps = compiled
                return compiled(*draws)

            self.compiled_steps = first
            return
        mode = "reduce-overhead" if self.device.type == "cuda" else None
        for name in self.compiled_losses:
            setattr(self, name, torch.compile(getattr(self, name), mode=mode))

    def functional_gradients(self) -> dict[str, Callable] | None:
        """The gradients :meth:`functional_steps` takes, by the attribute it reads them from
        (``{"critic_gradient": gradient_of(self.critic, self.critic_loss), ...}``), for an
        algorithm whose update has a functional form; None (the default): it has none."""
        return None

    def functional_steps(self, *draws) -> dict[str, torch.Tensor]:
        """:meth:`update`'s steps after its draws (the batch, the noise), with the gradients of
        :meth:`functional_gradients` and Adam and the guard as tensor ops, for
        ``torch.compile`` to take whole (``compile=true`` on the CPU)."""
        raise NotImplementedError

    # --- acting: one observation and one transition per member, in member order --------------
    def act_population(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        """``(K, act_dim)`` actions for ``(K, obs_dim)`` observations."""
        if explore and self.steps < self.random_until:  # uniform random warm-up
            return self.uniform_actions()
        noise = np.stack([m.noise.sample() for m in self.members]) if explore else None
        with torch.no_grad():
            obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
            return self.policy(obs_t.unsqueeze(1), noise)

    def uniform_actions(self) -> np.ndarray:
        """``(K, act_dim)`` uniform random actions, row k from member k's exploration stream:
        the numbers ``rng.uniform(low, high)`` draws (low + (high - low) u, in float64, from the
        same doubles u), without its per-call broadcasting of the bounds."""
        u = np.stack([m.rng.random(self.act_dim) for m in self.members])
        return (self._uniform_low + self._uniform_range * u).astype(np.float32)

    def policy(self, obs: torch.Tensor, noise: np.ndarray | None) -> np.ndarray:
        """``(K, act_dim)`` actions for ``(K, 1, obs_dim)`` observations; ``noise``: each
        member's exploration noise sample ``(K, act_dim)``, or None for the greedy policy."""
        raise NotImplementedError

    def store_steps(self, obs, actions, rewards, next_obs, terminated, episode_over) -> None:
        """One env step of every member, as ``(K, ...)`` arrays (``next_obs``: each member's own
        next observation, a finished episode's last): into the replay buffer, and a new episode's
        exploration noise for the members whose episode is over."""
        self.buffer.add(obs, actions, rewards, next_obs, terminated, episode_over)
        for i in np.flatnonzero(episode_over):
            self.members[i].noise.reset()
        self.steps += 1

    def observe_population(self, transitions: Sequence[Transition]) -> None:
        """:meth:`store_steps` for one :class:`Transition` per member."""
        fields = ("obs", "action", "reward", "next_obs", "terminated", "episode_over")
        self.store_steps(*(np.array([getattr(t, f) for t in transitions]) for f in fields))

    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        return self.act_population(obs[None], explore)[0]

    def observe(self, t: Transition) -> None:
        """A single agent's step: its fields broadcast as the one member's row."""
        self.store_steps(t.obs, t.action, t.reward, t.next_obs, t.terminated, t.episode_over)

    # --- learning: what every update shares -------------------------------------------------
    def update(self) -> dict[str, torch.Tensor]:
        """One gradient update, the algorithm's own (it starts with :meth:`begin_update`)."""
        raise NotImplementedError

    def begin_update(self) -> bool:
        """Whether it is time to learn (:meth:`ready_to_update`); if so, counts the update
        (:attr:`num_updates`: the delayed steps are every d-th)."""
        if not self.ready_to_update():
            return False
        self.num_updates += 1
        return True

    def ready_to_update(self) -> bool:
        """Past the warm-up, with a batch in the buffer."""
        return self.steps >= self.update_after and len(self.buffer) >= self.batch_size

    @property
    def update_period(self) -> int:
        """Updates after which the update's steps repeat (TD3's delayed step: every d-th):
        each residue of :attr:`num_updates` is one way through :meth:`update` (one captured
        graph)."""
        return 1

    def noise_like(self, x: torch.Tensor) -> torch.Tensor:
        """eps ~ N(0, I) shaped like ``x`` ``(K, ...)``, row k from member k's update-noise
        stream: every random number of an update is drawn here, outside the losses, so a
        compiled update draws the same numbers as eager (and a parity test can hand in another
        implementation's)."""
        return self.update_noise.normal_like(x)

    def record_health(
        self, bad: torch.Tensor, delayed_bad: torch.Tensor | None
    ) -> dict[str, torch.Tensor]:
        """Count this update's skipped steps (``delayed_bad``: the delayed step's, None when it
        did not run) and return the ``health/*`` metrics (``divergence_patience`` reads them)."""
        self.guard.record(bad, delayed_bad=delayed_bad)
        return self.guard.metrics()

    def q_values(self, critic: nn.Module, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Q_j(s, a) of every member's critics ``(K, C, N)`` for ``(K, N, d)`` inputs."""
        q = critic(self._per_critic(obs), self._per_critic(action))
        return q.unflatten(0, (self.population, self.num_critics))

    def q1(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Q_1(s, a) ``(K, N)``: each member's first critic alone (the deterministic policy
        gradient's critic)."""
        return self.critic(obs, action, members=slice(0, None, self.num_critics))

    @staticmethod
    def critics_regression(q: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Per-member critic loss ``(K,)``: the sum over its critics of N^-1 sum (y - Q_j)^2,
        for Q ``(K, C, N)`` and targets y ``(K, N)`` (constants)."""
        return (q - y.unsqueeze(1)).pow(2).mean(dim=2).sum(dim=1)

    def sample(self) -> Batch:
        """One mini-batch per member, drawn together: ``(K, batch, ...)`` tensors, with the
        rows each member drew from its buffer (``index``)."""
        return self.buffer.sample(self.batch_size)

    def _per_critic(self, x: torch.Tensor) -> torch.Tensor:
        """Each member's inputs once per critic: ``(K, N, d)`` -> ``(K * C, N, d)`` (a view for
        a single agent)."""
        return x.unsqueeze(1).expand(-1, self.num_critics, -1, -1).flatten(0, 1)

    # --- checkpoints: a single agent's is member 0 cut out, a population's its members' --------
    def state_dict(self, with_buffer: bool = False) -> dict:
        if self.population == 1:
            return self.member_state_dict(0, with_buffer)
        return {"members": [self.member_state_dict(i, with_buffer) for i in range(self.population)]}

    def load_state_dict(self, state: dict) -> None:
        for i, member_state in enumerate(state.get("members", [state])):
            self.load_member_state_dict(i, member_state)

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

    # --- a population's members one at a time: a single agent is a population of one, so member
    # i cut out is exactly a single agent's state_dict(), and a population's is the list of its
    # members'. A member's state loads into an ordinary agent (walkers.evaluate, walkers.collect,
    # resume= to continue it alone) or back into a population (resume=[id,id,...]).
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

    def member_policy(self, i: int) -> MemberAgent:
        """Member ``i`` as an agent of its own (evaluation rollouts, its checkpoints)."""
        return MemberAgent(self, i)

    def member_state_dict(self, i: int, with_buffer: bool = False) -> dict:
        """Member ``i`` of this agent as a single agent's ``state_dict()``: its slice of every
        per-member part (``self.member_cuts``: networks, targets, Adam moments, ...), its RNG,
        noise, buffer and guard counters; the shared counters."""
        state = {}
        for name, cut in self.member_cuts(i).items():
            part = getattr(self, name)
            if isinstance(part, torch.optim.Optimizer):
                optimizer_state = part.state_dict()
                for index, moments in list(optimizer_state["state"].items()):
                    # a new dict: state_dict() shares the live tensors
                    sliced = {key: moments[key][cut].clone() for key in ADAM_MOMENTS}
                    optimizer_state["state"][index] = moments | sliced
                state[name] = optimizer_state
            else:
                state[name] = {k: v[cut].clone() for k, v in part.state_dict().items()}
        shared = ("steps", "num_updates", "random_until", "update_after")
        return state | {
            **{key: getattr(self, key) for key in shared},
            **self.members[i].state_dict(),  # rng, noise
            "buffer": self.buffer.member_state_dict(i, with_buffer),
            "update_noise": self.update_noise.member_state_dict(i),
            "guard": self.guard.member_state_dict(i),
        }

    @torch.no_grad()
    def load_member_state_dict(self, i: int, state: dict) -> None:
        """Load a single agent's ``state_dict()`` into member ``i`` of this agent.

        Counters (env steps, updates, Adam's step count) are shared, so every member must be at the
        same update (``walkers.train`` checks); they are taken from the last member loaded.
        """
        for name, cut in self.member_cuts(i).items():
            part = getattr(self, name)
            if isinstance(part, torch.optim.Optimizer):
                _load_optimizer_member(part, cut, state[name]["state"])
            else:
                for key, value in part.state_dict().items():
                    value[cut] = state[name][key]
        self.load_counters(state)
        self.members[i].load_state_dict(state)
        self.buffer.load_member_state_dict(i, state["buffer"])
        if "update_noise" in state:  # saved before the update's noise had streams of its own
            self.update_noise.load_member_state_dict(i, state["update_noise"])
        self.guard.load_member_state_dict(i, state["guard"])
        self.refill_if_lost(state["buffer"])


def _load_optimizer_member(optimizer: torch.optim.Optimizer, cut: slice, saved_state: dict):
    """A member's Adam moments (``saved_state``: its optimizer ``state_dict()["state"]``) into
    the ``cut`` of ``optimizer``'s."""
    params = [p for group in optimizer.param_groups for p in group["params"]]
    for index, param in enumerate(params):  # the indices of optimizer.state_dict()
        if index not in saved_state:
            continue  # the member never stepped this parameter
        saved, live = saved_state[index], optimizer.state[param]
        if not live:  # a fresh optimizer: create its state as its first step would
            live["step"] = saved["step"].clone().to(param.device)
            live |= {key: torch.zeros_like(param) for key in ADAM_MOMENTS}
        for key in ADAM_MOMENTS:
            live[key][cut] = saved[key].to(param.device)
        live["step"].copy_(saved["step"])


class MemberAgent(Policy):
    """Member ``index`` of a population seen as an agent of its own: it acts greedily
    (evaluations) and checkpoints as a single agent; the population does the learning."""

    def __init__(self, population: ActorCritic, index: int):
        self.population, self.index = population, index
        self.members = slice(index, index + 1)
        self.device = population.device

    def act(self, obs: np.ndarray, explore: bool = False) -> np.ndarray:
        with torch.no_grad():
            obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
            action = self.population.actor(obs_t.view(1, 1, -1), members=self.members)[0, 0]
        return action.cpu().numpy().astype(np.float32)

    def state_dict(self, with_buffer: bool = False) -> dict:
        return self.population.member_state_dict(self.index, with_buffer)

    def load_state_dict(self, state: dict) -> None:
        self.population.load_member_state_dict(self.index, state)

    def resume_notes(self) -> dict[str, str]:
        return self.population.resume_notes()


# --- what each member has of its own: its RNG and exploration noise -------------------------
@dataclass
class Member:
    """What one member (one seed) has of its own besides its slices of the networks, the replay
    buffer and the update's noise streams."""

    rng: np.random.Generator  # uniform warm-up actions and exploration noise
    noise: GaussianNoise

    def state_dict(self) -> dict:
        return {"rng": self.rng.bit_generator.state, "noise": self.noise.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.rng.bit_generator.state = state["rng"]
        self.noise.load_state_dict(state["noise"])


# Exploration noise of the deterministic actor-critics (DDPG, TD3), one process per member.
class GaussianNoise:
    """i.i.d. N(0, sigma) exploration noise (TD3's)."""

    def __init__(self, sigma: float, size: int, rng: np.random.Generator):
        self.sigma, self.size, self.rng = sigma, size, rng

    def sample(self) -> np.ndarray:
        return self.rng.normal(0.0, self.sigma, self.size)

    def reset(self) -> None:
        pass

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass


class OrnsteinUhlenbeckNoise(GaussianNoise):
    """Temporally correlated noise x <- x + theta (0 - x) dt + sigma sqrt(dt) N(0, 1) (DDPG paper).

    Reset to zero at the start of every episode.
    """

    def __init__(self, sigma, size, rng, theta: float = 0.15, dt: float = 1e-2):
        super().__init__(sigma, size, rng)
        self.theta, self.dt = theta, dt
        self.x = np.zeros(size)

    def sample(self) -> np.ndarray:
        noise = self.rng.normal(0.0, 1.0, self.size)
        self.x = self.x - self.theta * self.x * self.dt + self.sigma * np.sqrt(self.dt) * noise
        return self.x

    def reset(self) -> None:
        self.x = np.zeros(self.size)

    def state_dict(self) -> dict:
        return {"x": self.x.copy()}

    def load_state_dict(self, state: dict) -> None:
        self.x = state["x"].copy()


NOISE_TYPES = {"gaussian": GaussianNoise, "ou": OrnsteinUhlenbeckNoise}


@contextmanager
def frozen(network: nn.Module) -> Iterator[None]:
    """No weight gradients for ``network`` inside (an actor's loss through the critics: the
    gradient flows through their input, the action, and their weights stay as they are)."""
    network.requires_grad_(False)
    try:
        yield
    finally:
        network.requires_grad_(True)


def logged(x: torch.Tensor) -> torch.Tensor:
    """A per-member ``(K,)`` diagnostic to log: a copy, as CUDA graphs reuse their outputs."""
    return x.detach().clone()
