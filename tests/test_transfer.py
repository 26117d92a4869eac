"""One upload and one read-back per prediction, and CUDA graphs that fall back cleanly."""

from __future__ import annotations

import logging
from collections import Counter

import numpy as np
import pytest
import torch

from saferace.learning import cuda_graphs, ensemble, networks, transfer
from saferace.learning.ensemble import StateEnsemble
from saferace.learning.networks import DrivingNetwork, control_config, state_config

#: The tensor methods that read a device's results back to the host (each a sync on CUDA).
READ_BACKS = ("cpu", "numpy", "item", "tolist")


def every_network() -> dict[str, object]:
    torch.manual_seed(0)
    heteroscedastic = dict(dropout=0.0, log_variance=True)
    return {
        "control, MC dropout": DrivingNetwork(control_config()).eval(),
        "state, MC dropout": DrivingNetwork(state_config()).eval(),
        "heteroscedastic": DrivingNetwork(state_config(**heteroscedastic)).eval(),
        "MIMO": DrivingNetwork(state_config(**heteroscedastic, subnetworks=3)).eval(),
        "packed": DrivingNetwork(state_config(**heteroscedastic, packed=(3, 1.0, 1))).eval(),
        "deep ensemble": StateEnsemble(
            [DrivingNetwork(state_config(**heteroscedastic)).eval() for _ in range(3)]
        ),
    }


@pytest.mark.parametrize("name", list(every_network()))
def test_a_prediction_uploads_its_frame_once_and_reads_its_results_back_once(name, monkeypatch):
    network = every_network()[name]
    calls: Counter[str] = Counter()

    def counted(label: str, function):
        def wrapper(*args, **kwargs):
            calls[label] += 1
            return function(*args, **kwargs)

        return wrapper

    for module in (networks, ensemble):
        monkeypatch.setattr(module, "upload", counted("upload", transfer.upload))
        monkeypatch.setattr(module, "download", counted("download", transfer.download))
    for method in READ_BACKS:
        monkeypatch.setattr(torch.Tensor, method, counted(method, getattr(torch.Tensor, method)))
    image = np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8)
    velocity = np.array([3.0, 0.1, 0.2], np.float32)
    prediction = network.predict(image, velocity, 10, torch.Generator().manual_seed(1))
    assert calls == Counter(upload=1, download=1, cpu=1, numpy=1)
    assert prediction.mean.shape == (1, len(network.config.outputs))
    assert np.all(np.isfinite(prediction.samples)) and prediction.features.shape[0] == 1


def test_packed_inputs_come_back_with_their_dtypes_shapes_and_values():
    image = torch.randint(0, 255, (1, 5, 7, 3), dtype=torch.uint8)
    velocity = torch.tensor([[3.0, -0.5, 0.25]])
    masks = torch.rand(10, 512) > 0.2
    parts = (image, velocity, masks)
    packed = transfer.pack(parts)
    assert packed.dtype == torch.uint8 and len(packed) % transfer.ALIGNMENT_BYTES == 0
    for original, unpacked in zip(parts, transfer.unpack(packed, parts), strict=True):
        assert unpacked.dtype == original.dtype and torch.equal(unpacked, original)


def test_results_come_back_as_float32_arrays_of_their_shapes():
    mean = torch.tensor([[1.0, 2.0]], dtype=torch.float64)
    samples = torch.arange(12, dtype=torch.bfloat16).reshape(1, 4, 3)
    back = transfer.download(mean, samples)
    assert [a.dtype for a in back] == [np.float32, np.float32]
    assert np.array_equal(back[0], [[1.0, 2.0]])
    assert np.array_equal(back[1], np.arange(12, dtype=np.float32).reshape(1, 4, 3))


def test_on_the_cpu_the_networks_run_eagerly_and_capture_no_graph():
    network = every_network()["packed"]
    image = np.random.default_rng(3).integers(0, 255, (2, 64, 64, 3), dtype=np.uint8)
    prediction = network.predict(image)
    with torch.inference_mode():
        eager = network.predict_tensors(torch.from_numpy(image))
    assert np.array_equal(prediction.samples, eager[2].numpy())
    assert not network._graphs._graphs
    assert not cuda_graphs.graphs_enabled(torch.device("cpu"))


def test_graphs_can_be_switched_off_and_a_failed_capture_runs_eagerly(monkeypatch, caplog):
    monkeypatch.setenv(cuda_graphs.GRAPHS_VARIABLE, "0")
    assert not cuda_graphs.graphs_enabled(torch.device("cuda"))
    monkeypatch.delenv(cuda_graphs.GRAPHS_VARIABLE)
    assert cuda_graphs.graphs_enabled(torch.device("cuda"))

    def no_capture(function, inputs):
        raise RuntimeError("operation not permitted when stream is capturing")

    monkeypatch.setattr(cuda_graphs, "graphs_enabled", lambda device: True)
    monkeypatch.setattr(cuda_graphs, "_Graph", no_capture)
    calls = []
    cache = cuda_graphs.GraphCache(lambda x: (calls.append(1) or x * 2,))
    with caplog.at_level(logging.WARNING):
        assert torch.equal(cache(torch.ones(2))[0], torch.full((2,), 2.0))
        assert torch.equal(cache(torch.ones(3))[0], torch.full((3,), 2.0))
    assert len(calls) == 2 and "capture failed" in caplog.text
    assert caplog.text.count("capture failed") == 1  # tried once, then eager
