"""A deep ensemble of state networks (Lakshminarayanan et al. 2017), beside MC dropout.

Each member is a whole state network (ResNet-18 features and a heteroscedastic head, see
:class:`~saferace.learning.networks.NetworkConfig`) trained from its own seed on the
Gaussian negative log-likelihood. The prediction is the members' mixture: the mean of their
means, and the variance ``mean(var_k) + var(mean_k)``: the members' own noise estimates
plus their disagreement, which grows on inputs unlike the training frames (where MC
dropout's spread measured nearly constant). Its samples are every member's two points
``mean_k +- std_k``, whose mean and population variance are exactly the mixture's, so a
filter that takes the samples' statistics sees the mixture.

Nothing is shared between the members: each runs its own backbone, so the cost of a
prediction grows with the members (``benchmarks/learned_step_speed.py`` measures it).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from saferace.errors import SafeRaceError
from saferace.learning.networks import DrivingNetwork, NetworkConfig, Prediction, mixture

#: Members of an ensemble by default (Lakshminarayanan et al. used 5).
DEFAULT_MEMBERS = 5


class StateEnsemble(nn.Module):
    """Heteroscedastic state networks predicting together; :meth:`predict` as a
    :class:`~saferace.learning.networks.DrivingNetwork`'s."""

    def __init__(self, members: list[DrivingNetwork]) -> None:
        super().__init__()
        if len(members) < 2:
            raise SafeRaceError(f"an ensemble needs at least 2 members, got {len(members)}")
        if any(not member.config.log_variance for member in members):
            raise SafeRaceError("ensemble members need heteroscedastic heads (log_variance)")
        if len({member.config for member in members}) != 1:
            raise SafeRaceError("ensemble members must share one network config")
        self.members = list(members)
        for index, member in enumerate(members):
            self.add_module(f"member_{index}", member)

    @property
    def config(self) -> NetworkConfig:
        return self.members[0].config

    @torch.inference_mode()
    def predict(
        self,
        image: np.ndarray | torch.Tensor,
        velocity: np.ndarray | torch.Tensor | None = None,
        n_samples: int = 10,
        generator: torch.Generator | None = None,
    ) -> Prediction:
        """The mixture's mean and std, with ``2 K`` samples and the members' features side by
        side (``n_samples`` and ``generator`` are a dropout network's: an ensemble is
        deterministic)."""
        predictions = [member.predict(image, velocity) for member in self.members]
        means = np.stack([p.mean for p in predictions])
        stds = np.stack([p.std for p in predictions])
        mean, std = mixture(means, stds)
        samples = np.concatenate([p.samples for p in predictions], axis=1)
        features = np.concatenate([p.features for p in predictions], axis=1)
        return Prediction(mean, std, samples, features)


#: What a state source predicts with: one network (MC dropout) or an ensemble.
StateNetwork = DrivingNetwork | StateEnsemble
