"""The one place agents are built: ``cfg.algo``'s ``_target_`` class with its hyperparameters
(with ``impl=sb3``: Stable-Baselines3's twin of that algorithm, with the same hyperparameters)."""

from __future__ import annotations

import hydra
from hydra.errors import InstantiationException
from omegaconf import DictConfig, OmegaConf

from walkers.agents.base import Agent, resolve_device
from walkers.agents.declarations.schemas import defaults, schema_of
from walkers.agents.sb3.twin import SB3Twin
from walkers.errors import ConfigError

#: Config-selected classes ``instantiate`` may build: agents only.
AGENT_TARGETS = ["walkers.agents.*"]


def build_agent(cfg: DictConfig, spaces: dict, **data) -> Agent:
    """Instantiate ``cfg.algo`` (its ``_target_`` class) for an env with ``spaces``, on
    ``cfg.device``, seeded with ``cfg.seed``.

    ``data``: what an offline agent learns from (``dataset=``); online agents take nothing more.
    """
    kwargs = OmegaConf.to_container(cfg.algo, resolve=True)
    name = kwargs.pop("name", None)
    if cfg.get("impl", "walkers") == "sb3":  # Stable-Baselines3's twin of the algorithm
        return SB3Twin(name, kwargs, **spaces, seed=cfg.seed, device=cfg.device)
    try:
        # partial, then called: Hydra would turn a dataset object into a config node
        factory = hydra.utils.instantiate(
            kwargs,
            **spaces,
            device=str(resolve_device(cfg.device)),
            seed=cfg.seed,
            _convert_="all",
            _partial_=True,
            _execution_whitelist_=AGENT_TARGETS,
        )
        return factory(**data)
    except (InstantiationException, ValueError, TypeError) as e:
        cause = e.__cause__ if isinstance(e, InstantiationException) else e
        if isinstance(cause, ValueError | TypeError):  # a bad or unknown hyperparameter
            raise ConfigError(f"algo.{cause}" if "=" in str(cause) else f"algo: {cause}") from None
        raise


def defaults_for(agent_class: type, **overrides) -> dict:
    """``agent_class``'s hyperparameters as constructor arguments: their declared defaults, with
    ``overrides`` (for code that builds an agent without a config: tests, benchmarks)."""
    return defaults(schema_of(f"{agent_class.__module__}.{agent_class.__qualname__}"), **overrides)
