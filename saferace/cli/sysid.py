"""``sysid``: identify the vehicle models' parameters from MuJoCo runs."""

from __future__ import annotations

import argparse
from pathlib import Path

from saferace.cli import example


def register(commands: argparse._SubParsersAction) -> None:
    sysid = commands.add_parser(
        "sysid",
        help="identify the vehicle-model parameters from MuJoCo runs",
        epilog=example("saferace sysid --out identified_params.json"),
    )
    sysid.add_argument(
        "--out", type=Path, default=None, help="parameter file (default: stored with the car)"
    )
    sysid.set_defaults(command=_sysid)


def _sysid(args: argparse.Namespace) -> int:
    from saferace.eval.tables import markdown_table
    from saferace.safety.vehicle_params import PARAMS_FILE
    from saferace.sysid.identify import identify

    result = identify()
    out = args.out or PARAMS_FILE
    result.params.to_json(out, extra=result.report())
    print(
        markdown_table(
            ["parameter", "value"], [[k, float(v)] for k, v in vars(result.params).items()]
        )
    )
    print()
    print(markdown_table(["fit residual", "RMS"], [[k, v] for k, v in result.residuals.items()]))
    print()
    rows = [
        [speed, model, errors["rms_e_y_m"], errors["rms_e_psi_rad"]]
        for speed, by_model in result.prediction.items()
        for model, errors in by_model.items()
    ]
    print("open-loop prediction error after 0.5 s (RMS over windows of the steering sweeps):")
    print(markdown_table(["speed", "model", "e_y [m]", "e_psi [rad]"], rows))
    print(f"parameters written to {out}")
    return 0
