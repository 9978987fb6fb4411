"""``algo.capture=true`` on CUDA: an off-policy agent's whole update as CUDA graphs.

One small update (TD3: about 40 kernels for a batch of 256) is bound by kernel launches on a GPU,
not by the GPU's arithmetic; ``torch.compile`` of the losses alone leaves the backward passes, the
optimizer steps, the guard and the target updates as launches of their own. LeanRL's lesson is to
capture the whole step: sampling the batch, the losses, backward, the fused optimizer steps, the
NaN guard and its counters, the delayed actor step and the target update. Everything an update
does is device work with no host sync (:mod:`walkers.seeding` draws the batch and the noise
with tensor ops; the guard counts on the device), so the algorithm's own :meth:`update`, as
written in its file, is what is captured: there is no second version of it to keep in step.

What an update does in Python is fixed by the update's number alone (the delayed step runs every
``update_period``-th update), so each residue of ``num_updates`` modulo the period is one way
through the update and one graph, captured the first time it comes, after a few eager warm-up
updates (on a side stream, as CUDA graphs ask). A replay is then one launch. Each graph keeps its
own memory pool (a few megabytes); its outputs (the losses to log) are copied out after each
replay, as the next replay overwrites them. Everything that lives from one update to the next
(weights, optimizer moments, the buffer, the streams' counts, the guard's counters) was made
before the first capture and is updated in place.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

#: Eager updates before the first capture: lazy initialisation (cuBLAS handles, the allocator's
#: first blocks, optimizer state) happens outside the graph.
WARMUP_UPDATES = 3


class CapturedUpdate:
    """Stands in for ``agent.update``: ``update`` (the algorithm's own, bound) runs eagerly for
    :data:`WARMUP_UPDATES` updates, then each way through it is captured once and replayed."""

    def __init__(self, agent, update: Callable[[], dict[str, torch.Tensor]]):
        self.agent, self.eager = agent, update
        self.graphs: dict[int, tuple[torch.cuda.CUDAGraph, dict[str, torch.Tensor]]] = {}
        self.warm_ups = 0  # eager updates done here (a resumed agent warms up again)
        self.side_stream = torch.cuda.Stream(device=agent.device)

    def __call__(self) -> dict[str, torch.Tensor]:
        agent = self.agent
        if not agent.ready_to_update():
            return {}
        if self.warm_ups < WARMUP_UPDATES:
            self.warm_ups += 1
            return self._on_side_stream(self.eager)
        path = (agent.num_updates + 1) % agent.update_period
        if path not in self.graphs:
            self.graphs[path] = self._capture()
        graph, outputs = self.graphs[path]
        graph.replay()
        agent.num_updates += 1  # what the update's begin_update does, outside the graph
        return {name: value.clone() for name, value in outputs.items()}

    def _on_side_stream(self, work: Callable[[], dict]) -> dict:
        stream, current = self.side_stream, torch.cuda.current_stream(self.agent.device)
        stream.wait_stream(current)
        with torch.cuda.stream(stream):
            out = work()
        current.wait_stream(stream)
        return out

    def _capture(self) -> tuple[torch.cuda.CUDAGraph, dict[str, torch.Tensor]]:
        """Record the next update (not run: its kernels run at each replay). Its Python side
        effect, counting the update, happens here once and is undone: each replay counts."""
        agent, graph = self.agent, torch.cuda.CUDAGraph()
        counted = agent.num_updates
        with torch.cuda.graph(graph):
            outputs = self.eager()
        agent.num_updates = counted
        return graph, outputs
