"""Parameters of the vehicle models, identified from the MuJoCo car and stored with it."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields
from importlib import resources
from pathlib import Path

PARAMS_FILE = Path(
    str(resources.files("saferace.assets.vehicles.rc10").joinpath("identified_params.json"))
)


@dataclass(frozen=True)
class VehicleParams:
    """Bicycle-model parameters of the rc10 (SI units).

    Cornering stiffness per axle is ``C = C_0 + D v_x`` (N/rad): MuJoCo's regularised
    friction acts on slip *velocity*, so the tyres' stiffness grows with speed (the usual
    constant-stiffness model is ``D = 0``). The defaults are first guesses;
    :func:`load_params` returns the ones identified from simulated runs by
    ``saferace sysid`` (see the car's README).
    """

    mass_kg: float = 3.5
    yaw_inertia_kgm2: float = 0.045
    lf_m: float = 0.162
    lr_m: float = 0.168
    cf0_npr: float = 0.0
    df_nspmr: float = 200.0
    cr0_npr: float = 0.0
    dr_nspmr: float = 200.0
    steer_time_constant_s: float = 0.05
    accel_time_constant_s: float = 0.05
    accel_gain: float = 1.0
    drag_per_s: float = 0.0

    @property
    def wheelbase_m(self) -> float:
        return self.lf_m + self.lr_m

    def to_json(self, path: str | Path, extra: dict | None = None) -> None:
        """Write the parameters (and e.g. the fit report) as JSON."""
        Path(path).write_text(
            json.dumps({"params": asdict(self), **(extra or {})}, indent=2) + "\n"
        )


def load_params(path: str | Path = PARAMS_FILE) -> VehicleParams:
    """Parameters from a JSON file written by :meth:`VehicleParams.to_json` (defaults if absent)."""
    path = Path(path)
    if not path.exists():
        return VehicleParams()
    stored = json.loads(path.read_text())["params"]
    names = {f.name for f in fields(VehicleParams)}
    return VehicleParams(**{k: v for k, v in stored.items() if k in names})
