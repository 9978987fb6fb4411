"""The dataset an offline run learns from, loaded once per session: the data, the references its
normalized scores are measured between, and its statistics as the params that say which data a
run learned from (:func:`walkers.training.provenance.dataset_params`)."""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from omegaconf import DictConfig

from walkers.training.evaluation import References, offline_references
from walkers.training.provenance import dataset_params
from walkers.training.validate import check_dataset_env

if TYPE_CHECKING:  # Minari is imported only when a dataset is used
    from walkers.data.datasets import OfflineData


@dataclass(frozen=True)
class RunDataset:
    dataset: OfflineData
    references: References

    @classmethod
    def load(cls, cfg: DictConfig) -> RunDataset:
        """``cfg.dataset``, checked against ``cfg.env``."""
        from walkers.data import datasets

        data = datasets.load(cfg.dataset)
        check_dataset_env(cfg, data)
        return cls(data, offline_references(cfg.env, data))

    @functools.cached_property
    def params(self) -> dict[str, str]:
        return dataset_params(self.dataset, self.references)


def loader() -> Callable[[DictConfig], RunDataset]:
    """:meth:`RunDataset.load`, once per dataset and env in a session (a plan may ask for the
    data to compare an earlier run's with, then to learn from)."""
    loaded: dict[tuple[str, str], RunDataset] = {}

    def load(cfg: DictConfig) -> RunDataset:
        key = (cfg.dataset, cfg.env.id)
        if key not in loaded:
            loaded[key] = RunDataset.load(cfg)
        return loaded[key]

    return load
