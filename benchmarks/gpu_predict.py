"""On a CUDA GPU: each network's prediction eager and replayed as CUDA graphs, and its copies.

For the control network and the state network with 10 MC-dropout samples, and the 5-member
deep and packed ensembles (random weights, one 64x64 mono frame): the median time of a
prediction with ``SAFERACE_CUDA_GRAPHS=0`` and with graphs, the largest difference of their
results (mean, std, samples, features: the graphs must give the eager results), and the
host-to-device and device-to-host copies of one prediction counted by the PyTorch profiler
(one of each: :mod:`saferace.learning.transfer`).

    python benchmarks/gpu_predict.py
"""

from __future__ import annotations

import os

import numpy as np
import torch
from learned_step_speed import ensemble, median_ms, networks, packed
from torch.profiler import ProfilerActivity, profile

from saferace.eval.tables import markdown_table
from saferace.learning.cuda_graphs import GRAPHS_VARIABLE
from saferace.learning.device import resolve_device

REPEATS = 100


def warm_median_ms(run) -> float:
    """The median of :data:`REPEATS` calls after a few (a graph is captured on its first)."""
    for _ in range(5):
        run()
    return median_ms(run, REPEATS)


def main() -> None:
    device = resolve_device("cuda")
    control, state = networks(stereo=False)
    made = {
        "control, MC dropout (10)": control,
        "state, MC dropout (10)": state,
        "deep ensemble (5)": ensemble(stereo=False),
        "packed ensemble (5)": packed(stereo=False),
    }
    image = np.random.default_rng(0).integers(0, 255, (64, 64, 3), np.uint8)
    velocity = np.array([3.0, 0.0, 0.5], np.float32)
    rows = []
    for name, network in made.items():
        network = network.to(device)

        def predict(network=network):
            speeds = velocity if network.config.uses_velocity else None
            return network.predict(image, speeds, 10, torch.Generator().manual_seed(0))

        os.environ[GRAPHS_VARIABLE] = "0"
        eager, eager_ms = predict(), warm_median_ms(predict)
        os.environ[GRAPHS_VARIABLE] = "1"
        graphed, graphs_ms = predict(), warm_median_ms(predict)
        fields = ("mean", "std", "samples", "features")
        difference = max(
            float(np.abs(getattr(eager, f) - getattr(graphed, f)).max()) for f in fields
        )
        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as profiler:
            predict()
            torch.cuda.synchronize(device)
        names = [event.name for event in profiler.events()]
        copies = [sum(kind in n for n in names) for kind in ("HtoD", "DtoH")]
        rows.append([name, eager_ms, graphs_ms, f"{difference:.1e}", *copies])
    columns = ["network", "eager [ms]", "CUDA graphs [ms]", "largest difference",
               "host-to-device copies", "device-to-host copies"]  # fmt: skip
    print(markdown_table(columns, rows))


if __name__ == "__main__":
    main()
