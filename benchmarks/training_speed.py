"""Training images per second of the control and the state network, and what changes it.

One Adam step on a batch of uint8 frames (normalised inside the network, channels-last)
is timed for both networks at 64x64, mono and stereo, and for a MIMO state network of 5
subnetworks; then, for the mono state network, the settings an issue asked about, each
against the default measured in the same run: ``torch.compile``, one thread instead of all,
batches of 64, and bfloat16 autocast on the CPU (alone and with batches of 64; it would
give up the CPU path's float32 results). Synthetic frames: the speed of a step does not
depend on what the images show. Target (issue 32): twice the images per second of the
default. A float32 step of ResNet-18 at 64x64 is about 0.9 GFLOP per image (0.3 forward),
so the default's rate is already near two cores' float32 peak; only a narrower type can
go past it.

With ``--device cuda`` (or ``auto`` where PyTorch sees a GPU) it prints instead the mono
state network's images per second on the CPU and the GPU side by side, at batches of 32
(the CPU recipe's) and 256, under the bfloat16 autocast that training uses on CUDA.

    python benchmarks/training_speed.py [--steps N] [--device auto|cpu|cuda]
"""

from __future__ import annotations

import argparse
import contextlib
import time

import torch

from saferace.eval.tables import markdown_table
from saferace.learning.device import autocast, resolve_device
from saferace.learning.networks import DrivingNetwork, control_config, state_config
from saferace.learning.training import training_loss

BATCH = 32
CPU = torch.device("cpu")
WARM_UP_STEPS = 3


def images_per_second(
    network: DrivingNetwork,
    steps: int,
    batch: int = BATCH,
    compiled: bool = False,
    bfloat16: bool = False,
    device: torch.device = CPU,
) -> float:
    """Frames per second of Adam steps on random frames of the network's input shape (on
    ``device``; on CUDA under training's bfloat16 autocast)."""
    config = network.config
    generator = torch.Generator().manual_seed(0)
    channels = config.in_channels * config.subnetworks
    images = torch.randint(
        0, 256, (batch, 64, 64, channels), dtype=torch.uint8, generator=generator
    ).to(device)
    velocity = torch.randn(batch, 3, generator=generator) if config.uses_velocity else None
    velocity = None if velocity is None else velocity.to(device)
    width = len(config.outputs)
    targets = torch.randn(batch, config.subnetworks, width, generator=generator).squeeze(1)
    targets = targets.to(device)
    network.to(device, memory_format=torch.channels_last)
    network.train()
    forward = torch.compile(network) if compiled else network
    optimizer = torch.optim.Adam(network.parameters(), lr=1e-3)

    def step() -> None:
        precision = (
            torch.autocast("cpu", dtype=torch.bfloat16)
            if bfloat16
            else autocast(device)
            if device.type == "cuda"
            else contextlib.nullcontext()
        )
        with precision:
            outputs = forward(images, velocity)
        loss = training_loss(network, outputs.float(), targets)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    for _ in range(WARM_UP_STEPS):
        step()
    start = time.perf_counter()
    for _ in range(steps):
        step()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return steps * batch / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--device", default="cpu", help="cpu, cuda, or auto (a GPU if any)")
    args = parser.parse_args()
    device = resolve_device(args.device)
    if device.type == "cuda":  # the CPU's levers below are the CPU recipe's
        side_by_side(device, args.steps)
        return
    networks = {
        "control, mono": control_config(),
        "control, stereo": control_config(stereo=True),
        "state, mono": state_config(),
        "state, stereo": state_config(stereo=True),
        "state, mono, MIMO(5)": state_config(log_variance=True, subnetworks=5),
    }
    rows = []
    for label, config in networks.items():
        torch.manual_seed(0)
        rows.append([label, images_per_second(DrivingNetwork(config), args.steps)])
    print(markdown_table(["network (64x64, batch 32)", "images/s"], rows))
    threads = torch.get_num_threads()
    default = rows[2][1]
    variants = []
    torch.manual_seed(0)
    compiled = images_per_second(DrivingNetwork(state_config()), args.steps, compiled=True)
    variants.append(["torch.compile", compiled])
    torch.set_num_threads(1)
    torch.manual_seed(0)
    variants.append(["1 thread", images_per_second(DrivingNetwork(state_config()), args.steps)])
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    batch_64 = images_per_second(DrivingNetwork(state_config()), args.steps, batch=64)
    variants.append(["batches of 64", batch_64])
    for label, batch in (("bfloat16 autocast", BATCH), ("bfloat16 autocast, batches of 64", 64)):
        torch.manual_seed(0)
        network = DrivingNetwork(state_config())
        variants.append([label, images_per_second(network, args.steps, batch, bfloat16=True)])
    table = [[f"default ({threads} threads, eager, batch 32)", default, "1.00x"]]
    table += [[label, rate, f"{rate / default:.2f}x"] for label, rate in variants]
    print(markdown_table(["state network, mono", "images/s", "vs default"], table))
    best = max(rate for _, rate in variants) / default
    print(f"target: 2x the default's images per second -> best {best:.2f}x, "
          f"{'met' if best >= 2.0 else 'MISSED'}")  # fmt: skip


def side_by_side(device: torch.device, steps: int) -> None:
    """The mono state network's images per second on the CPU and on ``device``."""
    rows = []
    for batch in (BATCH, 256):
        rates = []
        for where in (CPU, device):
            torch.manual_seed(0)
            network = DrivingNetwork(state_config())
            rates.append(images_per_second(network, steps, batch, device=where))
        rows.append([f"state, mono, batch {batch}", *rates, f"{rates[1] / rates[0]:.1f}x"])
    columns = ["network (64x64)", "CPU images/s", f"{device} images/s", "GPU / CPU"]
    print(markdown_table(columns, rows) + "\n")


if __name__ == "__main__":
    main()
