"""A benchmark submission's replay record: what ``saferace verify`` needs to drive its agent
again, the same way (its spec and settings, the faults it drove under, the hashes of the
files it loads, the device and compilation its networks ran with, the car's parameters)."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable

from saferace.errors import SafeRaceError
from saferace.eval.agents import agent_files
from saferace.eval.runner import file_sha256
from saferace.faults.spec import canonical_faults


def replay_record(agent: str, mc_samples: int, faults: Iterable[str] = ()) -> dict:
    """What ``saferace verify`` needs to drive ``agent`` again: its spec, its settings (the
    faults it drove under among them, where any), the sha256 of every file it loads and one
    hash of them all (the page's agent hash), the device its networks ran on and whether
    they ran compiled for the CPU (agents with files), and the sha256 of the car's
    identified parameters."""
    files = {}
    for path in agent_files(agent):
        if not path.is_file():
            raise SafeRaceError(f"agent {agent!r} loads {path}, which is not there")
        files[str(path)] = file_sha256(path)
    settings: dict = {"mc_samples": mc_samples}
    named = canonical_faults(list(faults))
    if named:  # absent without faults: fault-free hashes stay what they were
        settings["faults"] = list(named)
    identity = json.dumps({"agent": agent, **settings, "files": files}, sort_keys=True)
    return {
        "agent": agent,
        **settings,
        "files_sha256": files,
        "agent_sha256": hashlib.sha256(identity.encode()).hexdigest(),
        **network_settings(bool(files)),
        "vehicle_params_sha256": vehicle_params_sha256(),
    }


def network_settings(loads_files: bool) -> dict:
    """Where this process's networks run and whether compiled for the CPU, for a replay
    that ``loads_files`` (None for one that loads none: it runs no network of a file)."""
    return {
        "device": _network_device() if loads_files else None,
        "compiled": _networks_compiled() if loads_files else None,
    }


def replay_faults(replay: dict) -> tuple[str, ...]:
    """The faults a submission's runs drove under (none for one made without)."""
    return tuple(replay.get("faults", ()))


def _network_device() -> str:
    """Where this process's networks run (see ``saferace.learning.device``)."""
    from saferace.learning.device import resolve_device

    return str(resolve_device())


def _networks_compiled() -> bool:
    """Whether this process's networks run compiled (``saferace.learning.cpu_compile``)."""
    from saferace.learning.cpu_compile import compile_enabled
    from saferace.learning.device import resolve_device

    return compile_enabled(resolve_device())


def vehicle_params_sha256() -> str:
    """The sha256 of the car's identified parameters, which the expert and the filter use."""
    from saferace.safety.vehicle_params import PARAMS_FILE

    return file_sha256(PARAMS_FILE)
