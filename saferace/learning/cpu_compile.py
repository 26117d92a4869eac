"""Per-step network work compiled ahead of time for this CPU, its weights frozen in.

At batch 1 on a CPU, PyTorch's eager ResNet-18 spends more than half its time outside the
arithmetic: batch norms as their own passes, weights reordered for oneDNN on every call,
an operator dispatch per layer. AOTInductor with frozen weights folds the batch norms into
the convolutions, packs the weights once and runs the whole step as one compiled library:
on 2 cores a 5-member deep ensemble of 64x64 state networks measured 28-30 ms eager against
11-12 ms compiled, the MC-dropout control network 6 ms against 2.5.

:class:`CompiledStep` wraps a network's ``predict_tensors``: the first single-frame call of
a signature (shapes, dtypes and the number of threads) exports it (``torch.export``),
compiles it (``torch._inductor.aoti_compile_and_package``, freezing on) and keeps the
package in ``~/.cache/saferace/compiled`` (``SAFERACE_CACHE``), named by a hash of the
weights, the signature, the PyTorch version and the CPU's vector instructions: the next
run of the same network loads it in milliseconds. Compiling takes about 10 s a network
(20 s a 5-member ensemble), once, shown as progress; it pays after some 3,000 frames
(2.5 minutes of driving). A short run pays for it: the quick paper preset, whose DAgger
trains new networks every iteration, took 257 s against 216 eagerly. Changed weights
(training, ``load_state_dict``, an in-place edit) are seen from their tensors' version
counters and compile again.

It runs the function eagerly: off the CPU (CUDA has :mod:`saferace.learning.cuda_graphs`);
for a batch of frames (each batch size would be its own compile; a batch is efficient
eagerly); with ``SAFERACE_COMPILE=0``; and, after a warning naming the cause, where
compiling failed (no C++ compiler, say). Compiled results equal eager ones within float
tolerance (1e-5 here), not bit for bit, and a lap amplifies the difference: runs that must
reproduce an eager run exactly set ``SAFERACE_COMPILE=0``.
"""

from __future__ import annotations

import fcntl
import hashlib
import logging
import os
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

import torch
from torch import nn

from saferace.cache import cache_root
from saferace.names import COMPILE_VARIABLE
from saferace.progress import Progress

LOG = logging.getLogger(__name__)

#: Bump when what a package holds changes, so that old packages are not loaded.
PACKAGE_FORMAT = 1
#: The packages kept, at most (bytes; about 45 MB a ResNet-18): the least recently used go.
CACHE_LIMIT_BYTES = 2 * 1024**3

#: The inputs' shapes and dtypes, and the number of PyTorch threads.
Signature = tuple[tuple[tuple[tuple[int, ...], torch.dtype], ...], int]
_COMPILING = threading.Lock()  # one export and compile at a time in a process
_EAGER = threading.local()  # set inside :func:`eager_calls`, per thread
#: Finished packages' partial files older than this (s) are an interrupted compile's.
STALE_PARTIAL_S = 3600.0


def compile_enabled(device: torch.device) -> bool:
    """Whether networks on ``device`` run compiled (the CPU, unless switched off)."""
    return device.type == "cpu" and os.environ.get(COMPILE_VARIABLE, "1") != "0"


@contextmanager
def eager_calls() -> Iterator[None]:
    """Run this thread's predictions eagerly inside: for work on batches that may shrink to
    one frame (the last episode of a lockstep group, the last frame of a data set), which
    would compile a network for a few calls."""
    before = getattr(_EAGER, "on", False)
    _EAGER.on = True
    try:
        yield
    finally:
        _EAGER.on = before


def packages_folder() -> Path:
    return cache_root() / "compiled"


class _Step(nn.Module):
    """``owner.<method>`` as a module's forward: what ``torch.export`` takes."""

    def __init__(self, owner: nn.Module, method: str) -> None:
        super().__init__()
        self.owner = owner
        self.method = method

    def forward(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return tuple(getattr(self.owner, self.method)(*inputs))


class CompiledStep:
    """``owner.<method>(*tensors) -> tuple of tensors``, run from a compiled package per
    single-frame signature where :func:`compile_enabled`, else eagerly (see the module)."""

    def __init__(self, owner: nn.Module, method: str = "predict_tensors") -> None:
        self.owner = owner
        self.method = method
        self._runners: dict[Signature, Callable[..., list[torch.Tensor]]] = {}
        self._versions: tuple[tuple[int, int], ...] = ()
        self._modules: list[nn.Module] | None = None  # the owner's, walked once
        self._failed = False

    def __call__(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        eager = getattr(self.owner, self.method)
        single = inputs[0].shape[0] == 1 and not getattr(_EAGER, "on", False)
        if self._failed or not single or not compile_enabled(inputs[0].device):
            return eager(*inputs)
        inputs = tuple(tensor.contiguous() for tensor in inputs)  # the strides compiled for
        versions = self._weight_versions()
        if versions != self._versions:  # new weights: the frozen ones are stale
            self._runners.clear()
            self._versions = versions
        shapes = tuple((tuple(tensor.shape), tensor.dtype) for tensor in inputs)
        signature = (shapes, torch.get_num_threads())  # the threads are compiled in
        runner = self._runners.get(signature)
        if runner is None:
            try:
                with _COMPILING:
                    runner = self._load_or_compile(inputs, signature)
            except Exception as exc:  # the toolchain's, any kind: run eagerly from now on
                result = eager(*inputs)  # a bad input raises here, as it would eagerly
                LOG.warning("compiling %s failed (%s); it runs eagerly", self._name(), exc)
                self._failed = True
                return result
            self._runners[signature] = runner
        return tuple(runner(*inputs))

    def clear(self) -> None:
        """Forget the loaded packages (after the weights moved to another device)."""
        self._runners.clear()
        self._modules = None

    def __getstate__(self) -> dict:
        """A copy loads its own packages."""
        return {**self.__dict__, "_runners": {}, "_versions": (), "_modules": None}

    def _weight_versions(self) -> tuple[tuple[int, int], ...]:
        """Every weight's and buffer's storage and version counter: an in-place change
        through the tensor bumps its counter, a new tensor moves its storage. (A change
        through ``.data`` bumps neither: :meth:`clear` after one.) Read from each module's
        own tables, walked once: ``parameters()`` and ``buffers()`` took 5x as long, 0.7 ms
        a step for a 5-member ensemble."""
        if self._modules is None:
            self._modules = list(self.owner.modules())
        return tuple(
            (tensor.data_ptr(), tensor._version)
            for module in self._modules
            for table in (module._parameters, module._buffers)
            for tensor in table.values()
            if tensor is not None
        )

    def _name(self) -> str:
        return f"{type(self.owner).__name__}.{self.method}"

    def _load_or_compile(
        self, inputs: tuple[torch.Tensor, ...], signature: Signature
    ) -> Callable[..., list[torch.Tensor]]:
        """The package for these weights and ``signature``: from the cache, or exported,
        compiled and cached (written under a temporary name, then renamed: a failed or
        interrupted compile leaves no package half-written)."""
        path = packages_folder() / f"{self._key(signature)}.pt2"
        path.parent.mkdir(parents=True, exist_ok=True)
        with _locked(path.with_suffix(".lock")):  # another process compiling it: wait, load
            return self._load_or_compile_unlocked(inputs, path)

    def _load_or_compile_unlocked(
        self, inputs: tuple[torch.Tensor, ...], path: Path
    ) -> Callable[..., list[torch.Tensor]]:
        """:meth:`_load_or_compile` once it holds the package's lock."""
        if path.exists():
            try:
                runner = torch._inductor.aoti_load_package(str(path))
            except Exception:  # a damaged package: compile it again
                path.unlink(missing_ok=True)
            else:
                with suppress(OSError):  # pruned meanwhile by another process
                    os.utime(path)  # recently used
                return runner
        with (
            Progress(1, "compile for this CPU", "network") as bar,
            torch.inference_mode(False),
            torch.no_grad(),
        ):
            examples = tuple(tensor.clone() for tensor in inputs)  # not inference tensors
            program = torch.export.export(_Step(self.owner, self.method), examples)
            partial = path.with_name(f"{path.stem}.{os.getpid()}.partial.pt2")
            try:
                torch._inductor.aoti_compile_and_package(
                    program, package_path=str(partial), inductor_configs={"freezing": True}
                )
                partial.replace(path)
            finally:
                partial.unlink(missing_ok=True)
            bar.done(self._name(), f"kept in {path.parent} (SAFERACE_COMPILE=0 skips compiling)")
        runner = torch._inductor.aoti_load_package(str(path))
        with suppress(OSError):  # another process pruning at once
            prune_packages(path.parent, CACHE_LIMIT_BYTES)
        return runner

    def _key(self, signature: Signature) -> str:
        """A hash of everything the package depends on: the weights and buffers, the
        network's structure, the inputs' signature, PyTorch, the threads and the CPU."""
        digest = hashlib.blake2b(digest_size=20)
        isa = torch._inductor.cpu_vec_isa.pick_vec_isa()
        context = (PACKAGE_FORMAT, torch.__version__, str(isa))
        structure = (self.owner, getattr(self.owner, "config", None))
        digest.update(repr((context, self._name(), signature, structure)).encode())
        for name, tensor in self.owner.state_dict(keep_vars=True).items():
            digest.update(name.encode())
            flat = tensor.detach().cpu().contiguous().reshape(-1)
            digest.update(flat.view(torch.uint8).numpy().tobytes())
        return digest.hexdigest()


@contextmanager
def _locked(lock_path: Path) -> Iterator[None]:
    """Hold ``lock_path`` exclusively (across processes: workers that start together
    compile a network once, the others load it)."""
    with open(lock_path, "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def prune_packages(folder: Path, limit_bytes: int) -> None:
    """Delete the least recently used packages of ``folder`` until the rest fit ``limit_bytes``
    (a DAgger run compiles new networks every iteration), and the partial files of compiles
    interrupted, and the locks of packages deleted, more than :data:`STALE_PARTIAL_S` ago."""
    packages = []
    for path in folder.glob("*.pt2"):
        modified = path.stat().st_mtime
        if ".partial" not in path.suffixes:
            packages.append((modified, path))
        elif time.time() - modified > STALE_PARTIAL_S:
            path.unlink(missing_ok=True)
    for lock in folder.glob("*.lock"):  # of packages gone long ago
        old = time.time() - lock.stat().st_mtime > STALE_PARTIAL_S
        if old and not lock.with_suffix(".pt2").exists():
            lock.unlink(missing_ok=True)
    total = 0
    for _, path in sorted(packages, reverse=True):
        total += path.stat().st_size
        if total > limit_bytes:
            path.unlink(missing_ok=True)
