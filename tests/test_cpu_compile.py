"""Networks compiled for the CPU: the eager results within float tolerance, a package per
weights kept and reused, stale weights never used, and a clean fallback to eager."""

from __future__ import annotations

import copy
import logging
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from saferace.agents.pid import PIDSpeedController
from saferace.cache import CACHE_VARIABLE
from saferace.errors import SafeRaceError
from saferace.learning import cpu_compile
from saferace.learning.agent import LearnedAgent
from saferace.learning.ensemble import StateEnsemble
from saferace.learning.networks import DrivingNetwork, Prediction, control_config, state_config

IMAGE = np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8)
VELOCITY = np.array([3.0, 0.1, 0.2], np.float32)


@pytest.fixture
def compiling(monkeypatch, tmp_path):
    """Compiling on (the suite runs eagerly), into a cache of this test's own."""
    monkeypatch.setenv(cpu_compile.COMPILE_VARIABLE, "1")
    monkeypatch.setenv(CACHE_VARIABLE, str(tmp_path))
    return tmp_path / "compiled"


def predict(network, image: np.ndarray = IMAGE) -> Prediction:
    return network.predict(image, VELOCITY, 10, torch.Generator().manual_seed(1))


def eager_prediction(network, monkeypatch, image: np.ndarray = IMAGE) -> Prediction:
    with monkeypatch.context() as patch:
        patch.setenv(cpu_compile.COMPILE_VARIABLE, "0")
        return predict(network, image)


def assert_close(got: Prediction, expected: Prediction, tolerance: float) -> None:
    for name in ("mean", "std", "samples", "features"):
        np.testing.assert_allclose(
            getattr(got, name), getattr(expected, name), atol=tolerance, err_msg=name
        )


def networks() -> dict[str, torch.nn.Module]:
    torch.manual_seed(0)
    members = [DrivingNetwork(state_config(dropout=0.0, log_variance=True)) for _ in range(2)]
    return {
        "control, MC dropout": DrivingNetwork(control_config()).eval(),
        "deep ensemble": StateEnsemble([member.eval() for member in members]),
    }


class SmallNetwork(torch.nn.Module):
    """A convolution, a batch norm and a linear layer over a frame and the velocities: what
    the driving network is made of, compiled in seconds where a ResNet-18 takes 20 s."""

    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.convolution = torch.nn.Conv2d(3, 8, 5, stride=2)
        self.norm = torch.nn.BatchNorm2d(8)
        self.head = torch.nn.Linear(8 + 3, 2)

    def predict_tensors(self, image: torch.Tensor, velocity: torch.Tensor):
        x = image.permute(0, 3, 1, 2).float() / 255.0
        features = torch.relu(self.norm(self.convolution(x))).mean(dim=(2, 3))
        return self.head(torch.cat([features, velocity], dim=1)), features


def test_a_small_network_compiled_gives_the_eager_outputs_and_its_package_is_reused(
    compiling, monkeypatch
):
    network = SmallNetwork().eval()
    inputs = (torch.from_numpy(IMAGE)[None], torch.from_numpy(VELOCITY)[None])
    with torch.no_grad():
        expected = network.predict_tensors(*inputs)
        got = cpu_compile.CompiledStep(network)(*inputs)
    for a, b in zip(got, expected, strict=True):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    (package,) = compiling.glob("*.pt2")

    def no_compiling(*args, **kwargs):
        raise AssertionError("the same weights compiled twice")

    monkeypatch.setattr(torch._inductor, "aoti_compile_and_package", no_compiling)
    twin = cpu_compile.CompiledStep(copy.deepcopy(network))  # loaded from the disk
    eager_calls = []
    monkeypatch.setattr(SmallNetwork, "predict_tensors", lambda *a: eager_calls.append(1) or ())
    with torch.no_grad():
        again = twin(*inputs)
    assert not eager_calls and not twin._failed
    for a, b in zip(again, expected, strict=True):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    assert list(compiling.glob("*.pt2")) == [package]


# A ResNet-18 compiles in 15-30 s: the default suite stays within 15 min on 2 cores with the
# small network's compile above and the keys and loads checked with the compile faked below.
@pytest.mark.slow
@pytest.mark.parametrize("name", list(networks()))
def test_a_compiled_prediction_equals_the_eager_one_and_its_package_is_reused(
    name, compiling, monkeypatch
):
    network = networks()[name]
    expected = eager_prediction(network, monkeypatch)
    assert_close(predict(network), expected, 1e-5)
    (package,) = compiling.glob("*.pt2")
    eager_calls = []
    with monkeypatch.context() as patch:  # a compiled step never runs the network eagerly
        patch.setattr(network, "predict_tensors", lambda *inputs: eager_calls.append(1) or ())
        assert_close(predict(network), expected, 1e-5)
    assert not eager_calls

    def no_compiling(*args, **kwargs):
        raise AssertionError("the same weights compiled twice")

    monkeypatch.setattr(torch._inductor, "aoti_compile_and_package", no_compiling)
    twin = copy.deepcopy(network)  # the same weights: the package on disk is loaded
    assert_close(predict(twin), expected, 1e-5)
    assert list(compiling.glob("*.pt2")) == [package]


class FakeLoads:
    """Stands in for exporting and compiling: counts the loads, runs the step eagerly."""

    def __init__(self) -> None:
        self.keys: list[object] = []

    def __call__(self, step: cpu_compile.CompiledStep, inputs, signature):
        self.keys.append((signature, step._key(signature)))
        method = getattr(step.owner, step.method)

        def runner(*tensors: torch.Tensor) -> list[torch.Tensor]:
            # a package reads its inputs with the strides it was compiled for
            assert all(tensor.is_contiguous() for tensor in tensors)
            return list(method(*tensors))

        return runner


@pytest.fixture
def fake_loads(compiling, monkeypatch) -> FakeLoads:
    loads = FakeLoads()
    monkeypatch.setattr(
        cpu_compile.CompiledStep,
        "_load_or_compile",
        lambda step, inputs, signature: loads(step, inputs, signature),
    )
    return loads


def test_changed_weights_are_compiled_again(fake_loads):
    network = networks()["control, MC dropout"]
    predict(network)
    predict(network)
    assert len(fake_loads.keys) == 1
    with torch.no_grad():
        network.output_layer.bias.add_(1.0)  # an in-place edit, as an optimiser's step
    predict(network)
    assert len(fake_loads.keys) == 2
    assert fake_loads.keys[0][1] != fake_loads.keys[1][1]  # another package


def test_changed_buffers_are_compiled_again(fake_loads):
    """BatchNorm's running statistics are frozen into a package as weights are: a network
    trained on since (its buffers changed in place) runs from a new one."""
    network = networks()["control, MC dropout"]
    predict(network)
    batch_norm = next(m for m in network.modules() if isinstance(m, torch.nn.BatchNorm2d))
    assert batch_norm.running_mean is not None
    with torch.no_grad():
        batch_norm.running_mean.add_(0.1)
    predict(network)
    assert len(fake_loads.keys) == 2


def test_weights_loaded_as_new_tensors_are_compiled_again(fake_loads):
    network = networks()["control, MC dropout"]
    for _ in range(2):  # new tensors, each with version 0: only their storage tells
        state = {name: tensor.clone() for name, tensor in network.state_dict().items()}
        network.load_state_dict(state, assign=True)
        predict(network)
    assert len(fake_loads.keys) == 2


def test_the_package_key_is_every_part_of_what_it_was_compiled_from():
    """The key is the content: a copy of the network keys the same package; a weight, a
    buffer (BatchNorm's running mean, a normaliser's statistics), the network's config, the
    compiled method, the inputs' shapes, the threads and the CPU's vector instructions
    (a cache shared by two machines) each key another."""
    network = networks()["control, MC dropout"]
    signature = ((((1, 64, 64, 3), torch.uint8), ((1, 3), torch.float32)), 2)
    key = cpu_compile.CompiledStep(network)._key(signature)
    assert cpu_compile.CompiledStep(copy.deepcopy(network))._key(signature) == key
    changed = []
    for edit in ("weight", "buffer", "config"):
        other = copy.deepcopy(network)
        with torch.no_grad():
            if edit == "weight":
                other.output_layer.bias.add_(1e-3)
            elif edit == "buffer":
                batch_norm = next(m for m in other.modules() if isinstance(m, torch.nn.BatchNorm2d))
                assert batch_norm.running_mean is not None
                batch_norm.running_mean.add_(1e-3)
            else:
                other.config = control_config(dropout=0.5)
        changed.append(cpu_compile.CompiledStep(other)._key(signature))
    step = cpu_compile.CompiledStep(network, method="forward")
    changed.append(step._key(signature))
    (image, velocity), threads = signature
    changed.append(cpu_compile.CompiledStep(network)._key(((image, ((2, 3), torch.float32)), 2)))
    changed.append(cpu_compile.CompiledStep(network)._key(((image, velocity), threads + 1)))
    isa = torch._inductor.cpu_vec_isa
    with pytest.MonkeyPatch.context() as patch:  # another CPU's vector instructions
        patch.setattr(isa, "pick_vec_isa", lambda: "another CPU's instruction set")
        changed.append(cpu_compile.CompiledStep(network)._key(signature))
    assert len({key, *changed}) == 1 + len(changed)


def test_a_frame_that_is_a_strided_view_runs_from_contiguous_inputs(fake_loads, monkeypatch):
    network = networks()["control, MC dropout"]
    view = torch.from_numpy(IMAGE).permute(1, 0, 2)  # (64, 64, 3), not contiguous
    expected = eager_prediction(network, monkeypatch, view.numpy())
    assert_close(predict(network, view), expected, 1e-5)
    assert len(fake_loads.keys) == 1


def test_batches_in_eager_calls_stay_eager_when_they_shrink_to_one_frame(fake_loads):
    torch.manual_seed(0)
    network = DrivingNetwork(control_config()).eval()
    agents = [LearnedAgent(network, PIDSpeedController(0.05), 10, seed) for seed in range(2)]
    observation = {"image": IMAGE, "velocity": VELOCITY}
    LearnedAgent.act_together(agents, [observation, observation])
    LearnedAgent.act_together(agents[:1], [observation])  # the last episode still running
    with cpu_compile.eager_calls():
        predict(network)
    assert fake_loads.keys == []
    predict(network)  # outside, a driving step compiles
    assert len(fake_loads.keys) == 1


def test_a_bad_frame_raises_as_it_would_eagerly_and_compiling_stays_on(compiling):
    network = networks()["control, MC dropout"]
    with pytest.raises(SafeRaceError, match="expected images"):
        predict(network, np.zeros((64, 64, 4), np.uint8))
    assert not network._compiled._failed


def test_each_thread_count_has_its_own_package(fake_loads):
    network = networks()["control, MC dropout"]
    threads = torch.get_num_threads()
    predict(network)
    torch.set_num_threads(1 if threads > 1 else 2)
    try:
        predict(network)
    finally:
        torch.set_num_threads(threads)
    assert len(fake_loads.keys) == 2


def test_a_batch_of_frames_and_the_switched_off_step_run_eagerly(fake_loads, monkeypatch):
    network = networks()["control, MC dropout"]
    network.predict(np.stack([IMAGE, IMAGE]), np.stack([VELOCITY, VELOCITY]), 10)
    monkeypatch.setenv(cpu_compile.COMPILE_VARIABLE, "0")
    predict(network)
    assert fake_loads.keys == []


def test_a_failed_compile_warns_once_and_runs_eagerly(compiling, monkeypatch, caplog):
    network = networks()["control, MC dropout"]
    expected = eager_prediction(network, monkeypatch)

    def broken(*args, **kwargs):
        raise RuntimeError("no C++ compiler")

    monkeypatch.setattr(torch.export, "export", broken)
    with caplog.at_level(logging.WARNING, logger=cpu_compile.__name__):
        first, second = predict(network), predict(network)
    assert [record.getMessage() for record in caplog.records] == [
        "compiling DrivingNetwork.predict_tensors failed (no C++ compiler); it runs eagerly"
    ]
    assert_close(first, expected, 0.0)
    assert_close(second, expected, 0.0)
    assert not list(compiling.glob("*.pt2"))


def test_a_lock_is_pruned_only_long_after_its_package_went(tmp_path):
    """A package's lock without the package is a compile under way (its package not yet
    written) or one that went long ago: only an hour-old one is removed."""
    fresh, old = tmp_path / "fresh.lock", tmp_path / "old.lock"
    fresh.touch()
    old.touch()
    past = time.time() - 2.0 * cpu_compile.STALE_PARTIAL_S
    os.utime(old, (past, past))
    cpu_compile.prune_packages(tmp_path, 10**9)
    assert fresh.exists() and not old.exists()


def test_the_cache_keeps_the_most_recently_used_packages_within_its_limit(tmp_path):
    for age, name in enumerate(["newest", "middle", "oldest"]):
        (tmp_path / f"{name}.pt2").write_bytes(b"x" * 100)
        os.utime(tmp_path / f"{name}.pt2", (1e9 - age, 1e9 - age))
    (tmp_path / "other.123.partial.pt2").write_bytes(b"x" * 100)  # another process's, unfinished
    (tmp_path / "killed.45.partial.pt2").write_bytes(b"x" * 100)  # a compile killed long ago
    os.utime(tmp_path / "killed.45.partial.pt2", (1e9, 1e9))
    for name in ("newest", "gone"):  # the locks of a package and of one deleted long ago
        (tmp_path / f"{name}.lock").touch()
        os.utime(tmp_path / f"{name}.lock", (1e9, 1e9))
    cpu_compile.prune_packages(tmp_path, 250)
    left = sorted(path.name for path in tmp_path.iterdir())
    assert left == ["middle.pt2", "newest.lock", "newest.pt2", "other.123.partial.pt2"]


def test_a_compile_that_fails_half_way_leaves_no_package(compiling, monkeypatch):
    network = networks()["control, MC dropout"]

    def half_written(program, package_path, inductor_configs):
        Path(package_path).write_bytes(b"half a package")
        raise RuntimeError("out of disk")

    monkeypatch.setattr(torch._inductor, "aoti_compile_and_package", half_written)
    predict(network)  # runs eagerly, with a warning
    assert list(compiling.glob("*.pt2")) == []  # nor a partial one


def test_a_package_lock_is_held_by_one_at_a_time(tmp_path):
    order = []
    lock = tmp_path / "key.lock"

    def second() -> None:
        with cpu_compile._locked(lock):
            order.append("second")

    with cpu_compile._locked(lock):
        waiting = threading.Thread(target=second)
        waiting.start()
        time.sleep(0.2)  # the second has tried by now, and waits
        order.append("first")
    waiting.join()
    assert order == ["first", "second"]


def test_a_frame_of_another_dtype_runs_from_its_own_package(fake_loads):
    """A package reads its inputs as the dtypes it was compiled for: the same frame as
    floats is another signature, not the uint8 frame's package."""
    network = networks()["control, MC dropout"]
    image = torch.from_numpy(IMAGE)[None]
    velocity = torch.from_numpy(VELOCITY)[None]
    network._compiled(image, velocity)
    network._compiled(image.float(), velocity)
    network._compiled(image, velocity.double())
    dtypes = [tuple(dtype for _, dtype in signature[0]) for signature, _ in fake_loads.keys]
    assert dtypes == [
        (torch.uint8, torch.float32),
        (torch.float32, torch.float32),
        (torch.uint8, torch.float64),
    ]
    assert len({key for _, key in fake_loads.keys}) == 3


def test_a_fresh_machines_first_compiles_make_the_cache_folders(monkeypatch, tmp_path):
    """No cache yet (its parent folders neither): the first package makes them, and a
    second network's package goes into the folder the first made. Exporting and compiling
    stand in by a package file and the eager step."""
    root = tmp_path / "home" / "cache"
    monkeypatch.setenv(cpu_compile.COMPILE_VARIABLE, "1")
    monkeypatch.setenv(CACHE_VARIABLE, str(root))
    first = networks()["control, MC dropout"]
    second = copy.deepcopy(first)
    with torch.no_grad():
        second.output_layer.bias.add_(1.0)

    def package(program, package_path, inductor_configs):
        Path(package_path).write_bytes(b"a package")

    monkeypatch.setattr(torch.export, "export", lambda step, examples: step)
    monkeypatch.setattr(torch._inductor, "aoti_compile_and_package", package)
    monkeypatch.setattr(
        torch._inductor, "aoti_load_package", lambda path: lambda *t: [*first.predict_tensors(*t)]
    )
    for network in (first, second):
        predict(network)
        assert not network._compiled._failed
    assert len(list((root / "compiled").glob("*.pt2"))) == 2
