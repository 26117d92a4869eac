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
prediction grows with the members (``benchmarks/learned_step_speed.py`` measures it; a
packed ensemble, :mod:`saferace.learning.packed`, gives independent members at about one
network's cost). A prediction uploads the frame once, keeps every member's results and their
mixture on the device, and reads them back once; on CUDA all members replay as one graph.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from saferace.errors import SafeRaceError
from saferace.learning.cpu_compile import CompiledStep
from saferace.learning.cuda_graphs import GraphCache
from saferace.learning.networks import (
    DrivingNetwork,
    NetworkConfig,
    Prediction,
    frames,
    gaussian_samples,
)
from saferace.learning.transfer import download, upload

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
        self._compiled = CompiledStep(self)
        self._graphs = GraphCache(self._compiled)
        self._streams: list[torch.cuda.Stream] | None = None

    def _apply(self, fn, recurse=True):  # type: ignore[no-untyped-def]  # nn.Module's
        """Moving the weights (``to``, ``cuda``, ``half``) leaves captured graphs, compiled
        packages and the members' streams stale."""
        self._graphs.clear()
        self._compiled.clear()
        self._streams = None
        return super()._apply(fn, recurse)

    @property
    def device(self) -> torch.device:
        return self.members[0].device

    def __getstate__(self) -> dict:
        """A copy makes its own streams."""
        return {**super().__getstate__(), "_streams": None}

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
        on_device = upload(self.device, frames(image))
        return Prediction(*download(*self._graphs(*on_device)))

    def predict_tensors(self, image: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """:meth:`predict`'s work on the device: the mixture's mean and std, the samples and
        the members' features side by side, as tensors."""
        outputs = self._members_on(image)
        means = torch.cat([mean for mean, _, _ in outputs], dim=1)
        stds = torch.cat([std for _, std, _ in outputs], dim=1)
        return (*gaussian_samples(means, stds), torch.cat([f for _, _, f in outputs], dim=1))

    def _members_on(self, image: torch.Tensor) -> list[tuple[torch.Tensor, ...]]:
        """Every member's means, stds and features: on a GPU each member on its own
        stream, on the CPU one after another. (Side by side in threads they ran 20% faster
        on 2 cores, but OpenMP then throttled every later parallel region of the process: a
        MIMO step after them ran at 41 steps/s instead of 70.)"""
        if image.device.type == "cuda":
            return self._members_on_streams(image)
        return [_member_outputs(member, image) for member in self.members]

    def _members_on_streams(self, image: torch.Tensor) -> list[tuple[torch.Tensor, ...]]:
        """On a GPU every member on its own stream (in a captured graph, its own branch):
        at batch 1 one member leaves most of the GPU idle."""
        current = torch.cuda.current_stream(image.device)
        if self._streams is None:
            self._streams = [torch.cuda.Stream(image.device) for _ in self.members]
        outputs = []
        for member, stream in zip(self.members, self._streams, strict=True):
            stream.wait_stream(current)
            with torch.cuda.stream(stream):
                outputs.append(_member_outputs(member, image))
        for stream in self._streams:
            current.wait_stream(stream)
        return outputs


def _member_outputs(member: DrivingNetwork, image: torch.Tensor) -> tuple[torch.Tensor, ...]:
    features = member.features(image)
    return (*member.member_gaussians(member.head(features, None, False)), features)


#: What a state source predicts with: one network (MC dropout) or an ensemble.
StateNetwork = DrivingNetwork | StateEnsemble
