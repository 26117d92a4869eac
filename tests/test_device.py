"""Device selection: auto falls back to the CPU, a missing GPU is a clear error, and a
checkpoint saved from a GPU loads on the CPU."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from saferace.errors import SafeRaceError
from saferace.learning.checkpoint import load_checkpoint
from saferace.learning.device import resolve_device
from saferace.names import DEVICE_VARIABLE


@pytest.fixture
def no_gpu(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)


@pytest.fixture
def two_gpus(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)


def test_auto_takes_the_cpu_without_a_gpu(no_gpu, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.delenv(DEVICE_VARIABLE, raising=False)
    assert resolve_device() == resolve_device("auto") == torch.device("cpu")
    with pytest.raises(SafeRaceError, match="--device cuda: PyTorch sees no CUDA GPU"):
        resolve_device("cuda")


def test_auto_takes_a_gpu_where_torch_sees_one(two_gpus):
    assert resolve_device("auto") == torch.device("cuda")
    assert resolve_device("cuda:1") == torch.device("cuda", 1)
    assert resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(SafeRaceError, match=r"sees 2 CUDA GPU\(s\), cuda:0 to cuda:1"):
        resolve_device("cuda:2")
    with pytest.raises(SafeRaceError, match="use auto"):
        resolve_device("gpu")


def test_the_variable_carries_the_choice_to_workers(two_gpus, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setenv(DEVICE_VARIABLE, "cpu")
    assert resolve_device() == torch.device("cpu")


def test_the_command_line_refuses_a_gpu_it_cannot_see(tmp_path: Path):
    environment = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}
    result = subprocess.run(
        [sys.executable, "-m", "saferace", "train", str(tmp_path), "--out", "x.pt",
         "--device", "cuda"],
        capture_output=True, text=True, env=environment, check=False,
    )  # fmt: skip
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        "saferace train: error: --device cuda: PyTorch sees no CUDA GPU on this machine (a "
        "CPU-only build, no driver, or CUDA_VISIBLE_DEVICES empty); use --device cpu or auto"
    ]


def test_a_checkpoint_saved_from_a_gpu_loads_on_the_cpu(
    tiny_checkpoint, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    path, _ = tiny_checkpoint()
    payload = torch.load(path, map_location="cpu", weights_only=True)
    gpu_file = tmp_path / "from_gpu.pt"
    with monkeypatch.context() as patch:  # every storage tagged as a GPU's, as torch.save does
        patch.setattr(torch.serialization, "location_tag", lambda storage: "cuda:0")
        torch.save(payload, gpu_file)
    if not torch.cuda.is_available():
        with pytest.raises(RuntimeError, match="CUDA"):
            torch.load(gpu_file, weights_only=True)  # what a plain load does here
    loaded, reference = load_checkpoint(gpu_file, device="cpu"), load_checkpoint(path, "cpu")
    for network, expected in ((loaded.control, reference.control), (loaded.state, reference.state)):
        weights = network.state_dict()
        assert {tensor.device.type for tensor in weights.values()} == {"cpu"}
        assert all(
            torch.equal(weights[name], value) for name, value in expected.state_dict().items()
        )
