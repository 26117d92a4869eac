"""One training run's settings: optimisation, hold-out, initialisation, uncertainty.

Import-light (no torch), as :mod:`saferace.learning.configs`, which builds the DAgger and
collection configs on it.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from saferace.config import COUNT, NON_NEGATIVE, POSITIVE, Bounds, check_bounds, setting
from saferace.errors import ConfigError
from saferace.names import AUTO, STATE_UNCERTAINTY_METHODS

#: The networks a training run makes, in the order they are trained.
NETWORKS = ("control", "state")
#: How the learning rate moves over a training run.
LR_SCHEDULES = ("constant", "cosine")


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation, hold-out and initialisation of one training run.

    ``min_steps``: at least this many gradient steps, by adding epochs when the data are few
    (a DAgger run's first iterations train on a lap or two of frames: three epochs of them
    are a dozen steps, and the networks learn next to nothing). ``max_steps`` (0: none): at
    most this many, the last epoch cut short, so that a warm-started DAgger iteration costs
    the same however large the aggregate has grown. ``networks``: the networks trained; any
    other is taken unchanged from ``init``, or, the state network trained alone without one,
    left out (a perception model: :mod:`saferace.learning.perception`).
    """

    epochs: int = setting(10, "passes over the training frames per network", bounds=COUNT)
    min_steps: int = setting(
        0,
        "at least N gradient steps per training, adding epochs while the frames are few",
        flag="--min-train-steps",
        metavar="N",
        bounds=NON_NEGATIVE,
    )
    max_steps: int = setting(
        0,
        "at most N gradient steps per training (0: no bound), so that a warm-started "
        "iteration costs the same however large the aggregate",
        flag="--max-train-steps",
        metavar="N",
        bounds=NON_NEGATIVE,
    )
    batch_size: int = setting(32, "frames per Adam step", bounds=COUNT)
    learning_rate: float = setting(1e-3, "Adam's learning rate", flag="--lr", bounds=POSITIVE)
    lr_schedule: str = setting(
        "constant", "the learning rate: constant, or cosine from --lr to 0", choices=LR_SCHEDULES
    )
    seed: int = setting(0, "seeds the weights, the shuffling and the dropout", bounds=NON_NEGATIVE)
    val_stretch: tuple[float, float] | None = setting(
        (0.55, 0.7),
        "the stretch of the lap held out for validation, as fractions of the lap",
        metavar=("START", "END"),
        bounds=Bounds(minimum=0, maximum=1),
    )
    dropout: float = setting(0.2, "dropout of the heads", bounds=Bounds(minimum=0, below=1))
    init: str | None = setting(None, "warm-start from this checkpoint")
    backbone_weights: str | None = setting(
        None, "a torchvision ResNet-18 state dict (e.g. ImageNet) to start both backbones from"
    )
    state_uncertainty: str = setting(
        "mc-dropout",
        "the state network's uncertainty: MC dropout (the paper's), a deep ensemble of "
        "heteroscedastic networks, each from its own seed, a MIMO ensemble: heteroscedastic "
        "subnetworks in one ResNet-18, each trained on its own batches (one forward pass), or "
        "a packed ensemble: independent members in grouped layers (one forward pass)",
        choices=STATE_UNCERTAINTY_METHODS,
    )
    ensemble_members: int = setting(
        5,
        "state networks in an ensemble (subnetworks in a MIMO one, members in a packed one)",
        metavar="K",
        bounds=Bounds(minimum=2),
    )
    packed_alpha: float = setting(
        2.0, "a packed ensemble's width factor: each layer alpha times ResNet-18's", bounds=POSITIVE
    )
    packed_gamma: int = setting(
        1, "a packed ensemble's groups per member in each grouped convolution", bounds=COUNT
    )
    augment: bool = setting(
        False,
        "photometric augmentation: each training image redrawn with its own brightness, "
        "contrast, gamma, colour, noise and blur (saferace.learning.augmentation)",
    )
    patience: int = setting(
        0,
        "stop a network's training once its held-out loss has not improved for N epochs, "
        "and keep its best epoch's weights (0: train every epoch, keep the last)",
        flag="--early-stop",
        metavar="N",
        bounds=NON_NEGATIVE,
    )
    networks: tuple[str, ...] = NETWORKS

    def __post_init__(self) -> None:
        check_bounds(self)
        if self.state_uncertainty not in (*STATE_UNCERTAINTY_METHODS, AUTO):
            raise ConfigError(
                "state_uncertainty",
                f"must be one of {', '.join(STATE_UNCERTAINTY_METHODS)}, "
                f"got {self.state_uncertainty!r}",
            )
        start, end = self.val_stretch or (0.0, 1.0)
        if not 0.0 <= start < end <= 1.0:
            raise ConfigError(
                "val_stretch",
                f"must be fractions of the lap 0 <= start < end <= 1, got {self.val_stretch}",
            )
        if self.lr_schedule not in LR_SCHEDULES:
            raise ConfigError("lr_schedule", f"must be one of {LR_SCHEDULES}")
        if self.max_steps and self.min_steps > self.max_steps:
            raise ConfigError("min_steps", f"{self.min_steps} is above max_steps {self.max_steps}")
        if self.patience and self.val_stretch is None:
            raise ConfigError("patience", "needs held-out frames to stop on (a --val-stretch)")
        if not set(self.networks) <= set(NETWORKS) or not self.networks:
            raise ConfigError("networks", f"must be some of {NETWORKS}, got {self.networks}")
        if set(self.networks) != set(NETWORKS) and not self.init and "control" in self.networks:
            raise ConfigError(
                "init",
                "is needed: training only the control network takes the state network from it",
            )
        if self.init and self.backbone_weights:
            raise ConfigError(
                "backbone_weights", "and init both set the starting weights: choose one"
            )

    def as_dict(self) -> dict:
        return asdict(self)

    def steps_for(self, frames: int) -> int:
        """Gradient steps over ``frames`` training frames: ``epochs`` of them, or more to
        reach ``min_steps``, or fewer to stay within ``max_steps``."""
        batches = math.ceil(frames / self.batch_size)
        steps = batches * max(self.epochs, math.ceil(self.min_steps / batches))
        return min(steps, self.max_steps) if self.max_steps else steps
