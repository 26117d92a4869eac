"""One control step of the learned driver beside the expert's, and what each speed lever buys.

A learned step: render, the control network and the state network with ``n = 10`` MC-dropout
samples each (or, behind the robust filter: the generic perception model's size, one
heteroscedastic state network with its feature monitor; a 5-member deep, MIMO or packed
ensemble of state networks), the PID speed loop, and the filter's QP on the perceived state
(:class:`~saferace.safety.cbf.filter.SafetyFilter` fed by
:class:`~saferace.learning.agent.LearnedStateSource`), then physics. The baseline, measured
in the same run: the expert MPC's step on ground truth (render, MPC, physics). Networks
have random weights (the time does not depend on them). Targets: at least 50 learned steps/s
at 64x64 mono on 2 cores, 55 with the packed ensemble and 35 with the deep ensemble; on a
CUDA GPU, 250 with either 5-member ensemble. ``--device auto`` (the default) measures the
CPU and, where PyTorch sees one, the GPU side by side (the env and the filter stay on the
CPU; on CUDA the networks replay CUDA graphs, :mod:`saferace.learning.cuda_graphs`).

On the CPU the networks run compiled (:mod:`saferace.learning.cpu_compile`; each step's
first prediction compiles them: the medians leave that out). The next tables time the
control network's inference alone, from the naive way (the whole network once per MC
sample, NCHW, autograd on) adding one lever at a time: one backbone pass with the head
sampled in one batch, inference mode, channels-last, compiled with frozen weights; and the
same on one thread. The last table times the deep ensemble's backbones one after another
eagerly, under bfloat16 autocast, and two members at a time on one thread each (faster,
but threads left OpenMP throttling the rest of the process, so ``predict`` does not), then
its whole prediction compiled.

    python benchmarks/learned_step_speed.py [--steps N] [--track NAME] [--device auto|cpu|cuda]
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ThreadPoolExecutor

import gymnasium as gym
import numpy as np
import torch

import saferace  # noqa: F401  - registers the tasks
from saferace.agents.mpc import MPCExpert
from saferace.agents.pid import PIDSpeedController
from saferace.eval.agents import act
from saferace.eval.tables import markdown_table
from saferace.learning.agent import LearnedAgent, LearnedStateSource
from saferace.learning.configs import TrainConfig
from saferace.learning.device import resolve_device
from saferace.learning.ensemble import DEFAULT_MEMBERS, StateEnsemble
from saferace.learning.networks import DrivingNetwork, control_config, state_config
from saferace.names import CONFORMAL_ALPHA
from saferace.safety.cbf.filter import SafetyFilter
from saferace.safety.uncertainty.conformal import ConformalCalibration, fit_feature_monitor
from saferace.safety.uncertainty.intervals import ConformalStateSource

TARGET_STEPS_PER_S = 50.0
#: Steps per second each ensemble must reach, on the CPU (2 cores) and on a CUDA GPU.
ENSEMBLE_TARGETS = {
    "packed": {"cpu": 55.0, "cuda": 250.0},
    "ensemble": {"cpu": 35.0, "cuda": 250.0},
}
MC_SAMPLES = 10


def networks(stereo: bool) -> tuple[DrivingNetwork, DrivingNetwork]:
    torch.manual_seed(0)
    made = []
    for config in (control_config(stereo), state_config(stereo)):
        made.append(DrivingNetwork(config).eval().to(memory_format=torch.channels_last))
    return made[0], made[1]


def step_times_ms(env: gym.Env, agent, steps: int) -> np.ndarray:
    """Wall time of ``agent.act`` + ``env.step`` per step; a new episode when one ends."""
    observation, info = env.reset(seed=0)
    times = []
    for _ in range(steps):
        started = time.perf_counter()
        observation, _, terminated, truncated, info = env.step(act(agent, observation, info))
        times.append(time.perf_counter() - started)
        if terminated or truncated:
            observation, info = env.reset(seed=0)
            agent.reset()
    return np.array(times[10:]) * 1e3  # without the first steps' warm-up


def ensemble(stereo: bool, members: int = DEFAULT_MEMBERS) -> StateEnsemble:
    """An ensemble of heteroscedastic state networks (random weights)."""
    made = []
    for index in range(members):
        torch.manual_seed(100 + index)
        member = DrivingNetwork(state_config(stereo, dropout=0.0, log_variance=True))
        made.append(member.eval().to(memory_format=torch.channels_last))
    return StateEnsemble(made)


def mimo(stereo: bool, members: int = DEFAULT_MEMBERS) -> DrivingNetwork:
    """A MIMO ensemble: ``members`` heteroscedastic subnetworks in one ResNet-18."""
    torch.manual_seed(100)
    config = state_config(stereo, dropout=0.0, log_variance=True, subnetworks=members)
    return DrivingNetwork(config).eval().to(memory_format=torch.channels_last)


def packed(stereo: bool, members: int = DEFAULT_MEMBERS) -> DrivingNetwork:
    """A packed ensemble: ``members`` independent members, the default alpha and gamma."""
    torch.manual_seed(100)
    packing = (members, TrainConfig.packed_alpha, TrainConfig.packed_gamma)
    config = state_config(stereo, dropout=0.0, log_variance=True, packed=packing)
    return DrivingNetwork(config).eval().to(memory_format=torch.channels_last)


def generic(stereo: bool, device: str = "cpu") -> ConformalStateSource:
    """The generic perception model's size and per-step work: one heteroscedastic network
    with a conformal interval and a feature monitor (fitted on random features)."""
    torch.manual_seed(100)
    network = DrivingNetwork(state_config(stereo, dropout=0.0, log_variance=True))
    network = network.eval().to(device, memory_format=torch.channels_last)
    features = np.random.default_rng(0).normal(size=(400, 512))
    monitor = fit_feature_monitor(features, CONFORMAL_ALPHA)
    calibration = ConformalCalibration(CONFORMAL_ALPHA, 2.0, len(features), monitor)
    return ConformalStateSource(LearnedStateSource(network, 1, seed=0), calibration)


def learned_env(
    track: str, stereo: bool, state_uncertainty: str = "mc-dropout", device: str = "cpu"
) -> tuple[gym.Env, LearnedAgent]:
    """The learned step: MC dropout behind the chance-constrained filter, or behind the
    robust one the generic model's size or a deep, MIMO or packed ensemble (their interval
    ``mean +- 2 std``: the conformal scale's cost is the same); networks on ``device``."""
    control, state = (network.to(device) for network in networks(stereo))
    env = gym.make("saferace/CenterLine-v0", track=track, stereo=stereo, max_laps=100)
    if state_uncertainty == "generic":
        env = SafetyFilter(env, state_source=generic(stereo, device), uncertainty="robust")
    elif state_uncertainty != "mc-dropout":
        made = {"ensemble": ensemble, "mimo": mimo, "packed": packed}[state_uncertainty](stereo)
        source = LearnedStateSource(made.to(device), MC_SAMPLES, seed=0)
        env = SafetyFilter(env, state_source=source, uncertainty="robust")
    else:
        env = SafetyFilter(env, state_source=LearnedStateSource(state, MC_SAMPLES, seed=0))
    agent = LearnedAgent(control, PIDSpeedController(env.unwrapped.control_dt_s), MC_SAMPLES)
    return env, agent


def median_ms(run, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        run()
        times.append(time.perf_counter() - started)
    return float(np.median(times) * 1e3)


def lever_times_ms(network: DrivingNetwork, image: np.ndarray, velocity: np.ndarray) -> list:
    """One frame with ``MC_SAMPLES`` samples, each lever added to the one before."""
    nchw = DrivingNetwork(network.config)  # weights in NCHW memory
    nchw.load_state_dict(network.state_dict())
    nchw.eval()
    nchw_image = torch.from_numpy(image[None]).permute(0, 3, 1, 2).contiguous().permute(0, 2, 3, 1)
    nhwc_image = torch.from_numpy(image[None])
    v = torch.from_numpy(velocity[None]) if network.config.uses_velocity else None

    def whole_network_per_sample() -> None:
        for _ in range(MC_SAMPLES):
            nchw.head(nchw.features(nchw_image), v, sample=True)

    def shared_backbone(model: DrivingNetwork, images: torch.Tensor) -> None:
        features = model.features(images).repeat_interleave(MC_SAMPLES, 0)
        model.head(features, None if v is None else v.repeat_interleave(MC_SAMPLES, 0), True)

    def in_inference_mode(model: DrivingNetwork, images: torch.Tensor) -> None:
        with torch.inference_mode():
            shared_backbone(model, images)

    levers = [
        ("whole network per sample, NCHW, autograd on", whole_network_per_sample),
        (
            "+ one backbone pass, head sampled in one batch",
            lambda: shared_backbone(nchw, nchw_image),
        ),
        ("+ inference mode", lambda: in_inference_mode(nchw, nchw_image)),
        ("+ channels-last", lambda: in_inference_mode(network, nhwc_image)),
    ]
    times = [(label, median_ms(run, 30)) for label, run in levers]
    network.predict(image, velocity, MC_SAMPLES)  # compiles (or loads) before timing
    compiled = median_ms(lambda: network.predict(image, velocity, MC_SAMPLES), 30)
    return [*times, ("+ compiled for this CPU, weights frozen (what predict() does)", compiled)]


def devices_of(spec: str) -> list[str]:
    """``auto``: the CPU, and CUDA beside it where PyTorch sees a GPU; else the one named."""
    if spec == "auto":
        return ["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"]
    return [str(resolve_device(spec))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--track", default="lab")
    parser.add_argument("--device", default="auto", help="auto (CPU, and GPU if any), cpu, cuda")
    args = parser.parse_args()
    devices = devices_of(args.device)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, devices {devices}")

    expert_env = gym.make("saferace/CenterLine-v0", track=args.track, max_laps=100)
    expert = MPCExpert.for_env(expert_env)
    baseline_times = step_times_ms(expert_env, expert, args.steps)
    expert_env.close()
    rows = [["expert MPC, ground truth (baseline)", "-", baseline_times]]
    kinds = {
        "generic": "the generic perception model's size (one heteroscedastic network)",
        "ensemble": f"{DEFAULT_MEMBERS}-member deep ensemble",
        "mimo": f"{DEFAULT_MEMBERS}-member MIMO ensemble",
        "packed": f"{DEFAULT_MEMBERS}-member packed ensemble",
    }
    runs = [(False, "mc-dropout"), (True, "mc-dropout"), *((False, kind) for kind in kinds)]
    verdicts = []
    for device in devices:
        for stereo, uncertainty in runs:
            env, agent = learned_env(args.track, stereo, uncertainty, device)
            camera = "stereo 64x64x6" if stereo else "mono 64x64x3"
            label = (
                f"learned, {camera}, perceived-state filter"
                if uncertainty == "mc-dropout"
                else f"learned, {camera}, {kinds[uncertainty]}, robust filter"
            )
            times = step_times_ms(env, agent, args.steps)
            rows.append([label, device, times])
            env.close()
            if not stereo:
                verdicts.append((uncertainty, device, 1e3 / np.median(times)))
    baseline = np.median(baseline_times)
    table = []
    for label, device, times in rows:
        median = np.median(times)
        table.append(
            [label, device, median, np.percentile(times, 95), 1e3 / median, median / baseline]
        )
    columns = ["step", "networks on", "median [ms]", "p95 [ms]", "steps/s", "x expert's time"]
    print(markdown_table(columns, table))
    for uncertainty, device, rate in verdicts:
        kind = device.split(":")[0]
        one_network = uncertainty in ("mc-dropout", "generic")
        default = TARGET_STEPS_PER_S if kind == "cpu" and one_network else None
        target = ENSEMBLE_TARGETS.get(uncertainty, {}).get(kind, default)
        if target is not None:
            verdict = "meets" if rate >= target else "misses"
            name = f"mono, {uncertainty}, networks on {device}"
            print(f"\n{name}: {rate:.0f} steps/s, {verdict} the target of {target:.0f}")
    print()
    if "cpu" not in devices:
        return

    velocity = np.array([3.0, 0.0, 0.5], np.float32)
    for stereo in (False, True):
        image = np.random.default_rng(0).integers(0, 256, (64, 64, 6 if stereo else 3), np.uint8)
        control, _ = networks(stereo)
        levers = lever_times_ms(control, image, velocity)
        levers.append(one_thread_ms(control, image, velocity))
        camera = "stereo 64x64x6" if stereo else "mono 64x64x3"
        print(f"control network, one {camera} frame, {MC_SAMPLES} MC samples:")
        first = levers[0][1]
        lines = [[label, ms, first / ms] for label, ms in levers]
        print(markdown_table(["lever", "median [ms]", "speed-up"], lines) + "\n")
    image = np.random.default_rng(0).integers(0, 256, (64, 64, 3), np.uint8)
    levers = ensemble_lever_times_ms(image)
    print(f"{DEFAULT_MEMBERS}-member deep ensemble's backbones, one mono 64x64x3 frame:")
    first = levers[0][1]
    lines = [[label, ms, first / ms] for label, ms in levers]
    print(markdown_table(["lever", "median [ms]", "speed-up"], lines) + "\n")


def ensemble_lever_times_ms(image: np.ndarray) -> list[tuple[str, float]]:
    """The deep ensemble's backbones on one frame: one after another, eagerly, under
    bfloat16 autocast, and two members at a time on one thread each; then its whole
    prediction compiled for this CPU (what ``predict`` does)."""
    made = ensemble(stereo=False)
    members = made.members
    frame = torch.from_numpy(image[None])
    threads = torch.get_num_threads()

    @torch.inference_mode()
    def features(member: DrivingNetwork, dtype: torch.dtype | None = None) -> torch.Tensor:
        with torch.autocast("cpu", dtype=dtype or torch.bfloat16, enabled=dtype is not None):
            return member.features(frame)

    def in_pairs() -> None:
        torch.set_num_threads(1)
        try:
            list(pool.map(features, members))
        finally:
            torch.set_num_threads(threads)

    with ThreadPoolExecutor(2) as pool:
        levers = [
            ("one after another, eager", lambda: [features(m) for m in members]),
            ("bfloat16 autocast", lambda: [features(m, torch.bfloat16) for m in members]),
            ("two members at a time, one thread each", in_pairs),
        ]
        times = [(label, median_ms(run, 30)) for label, run in levers]
    made.predict(image)  # compiles (or loads) before timing
    compiled = median_ms(lambda: made.predict(image), 30)
    return [*times, ("the whole prediction compiled for this CPU (what predict() does)", compiled)]


def one_thread_ms(network: DrivingNetwork, image: np.ndarray, velocity: np.ndarray) -> tuple:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        network.predict(image, velocity, MC_SAMPLES)  # compiles for one thread
        single = median_ms(lambda: network.predict(image, velocity, MC_SAMPLES), 30)
    finally:
        torch.set_num_threads(threads)
    return f"(the same on 1 thread instead of {threads})", single


if __name__ == "__main__":
    main()
