"""The safety layer: four concerns, a sub-package each, on shared vehicle models.

- :mod:`saferace.safety.cbf`: the control-barrier-function filter (``SafetyFilter``): the
  lane and speed barriers, their QP and its solvers, the chance constraints.
- :mod:`saferace.safety.predictive`: the predictive safety filter (``--filter mpsf``).
- :mod:`saferace.safety.uncertainty`: what the filters know of the lane state and how much
  to trust it: state sources, conformal intervals, the feature monitor, adaptive intervals,
  odometry fusion, the carried (dead-reckoned) set and the fallback.
- :mod:`saferace.safety.traffic`: the barriers that keep the car clear of other cars.

Shared by them and by the expert MPC: the vehicle models (:mod:`~saferace.safety.models`,
:mod:`~saferace.safety.vehicle_params`, :mod:`~saferace.safety.matrix_exponential`), the
linear time-varying MPC (:mod:`~saferace.safety.ltv_mpc`), what passes through a filter
(:mod:`~saferace.safety.decision`) and the protocol a filter of one's own follows
(:mod:`~saferace.safety.filter_protocol`).
"""
