"""The control-barrier-function safety filter: barriers, their QP, its solvers."""
