"""The one home of SafeRace's names and shared defaults.

Import-free on purpose: the command line, the configs and the heavy modules (the filter,
the networks, the experiments) all read their choices and defaults here, so that a name
or a default cannot drift between two copies.
"""

from __future__ import annotations

#: The half length and half width of the rc10's ``bumper`` box (m, ``rc10.xml``; a test
#: checks the model): where two cars touch, for the contact check and the car barriers.
RC10_BUMPER_HALF_EXTENTS_M = (0.225, 0.155)

#: The tasks by short name, and their gymnasium ids.
#: The endings a video is written with: H.264 in MP4, VP8 in WebM (both play in browsers).
VIDEO_SUFFIXES = (".mp4", ".webm")
TASK_IDS = {"CenterLine": "saferace/CenterLine-v0", "RacingLine": "saferace/RacingLine-v0"}
TASKS: tuple[str, ...] = tuple(TASK_IDS)
#: Tasks in traffic (``saferace.envs.traffic``): they start among opponents.
TRAFFIC_TASK_IDS = {"Overtake": "saferace/Overtake-v0"}
#: Every task a driver can be run, collected or trained on.
DRIVING_TASKS: tuple[str, ...] = (*TASKS, *TRAFFIC_TASK_IDS)
#: The sensor and actuator faults' form on the command line (``saferace.faults``).
#: The drivers of ``saferace faults``: the reckless ones and the expert (a learned driver
#: joins them as ``learned:CHECKPOINT``).
FAULT_TABLE_DRIVERS = ("drift", "weave", "speeding", "expert")
FAULTS_HELP = (
    "sensor and actuator faults, seeded by the episode: blackout, frozen, dropped, latency, "
    "occlusion, flicker, odometry, steering, delay, each with start=S, duration=S, severity=1-3 "
    "and its own sizes (blackout:start=3,duration=2 latency:steps=2)"
)
#: The ``info`` key under which a fault wrapper gives the pose its faulty odometry integrated
#: (``saferace.faults``), what a filter carries its set by; without it, the true pose's.
ODOMETRY_POSE_KEY = "odometry_pose"
#: The attribute by which a task's wrapper declares how far off, as a fraction, its car's
#: odometry may measure distance and turn (its datasheet's, never whether a fault acts): the
#: filter carries its sets for it. Without one, the simulator's odometry is exact.
ODOMETRY_ERROR_ATTRIBUTE = "odometry_scale_error"
#: The attribute by which a task's wrappers declare the most control steps its actuators
#: may apply a command late (the delay fault's; none: at once).
ACTUATION_DELAY_ATTRIBUTE = "actuation_delay_steps"
#: The attribute by which a task's wrappers declare the most control steps its camera's
#: frames may arrive late (the latency fault's; none: each frame is its step's).
CAMERA_LATENCY_ATTRIBUTE = "camera_latency_steps"
#: The opponent specs' form on the command line and in configs.
OPPONENTS_HELP = (
    "other cars on track, POLICY[:FIELD=VALUE,...]: expert, racer, pure-pursuit, lane-changer, "
    "blocker, braking, external (the caller's actions; fields gap_m, start_offset_m, "
    "speed_factor, lateral_offset_m)"
)

#: Vehicle models of the expert MPC and the safety filter (``saferace.safety.models``).
VEHICLE_MODELS = ("kinematic", "dynamic", "dynamic-paper")
DEFAULT_EXPERT_MODEL = "dynamic"
#: Each filter family's vehicle model unless one is named: the CBF's barriers are the
#: paper's kinematic ones; the predictive filter's plan needs the tyres' slip at speed
#: (on its kinematic model the speeding agent left the lane on ``lab``).
DEFAULT_FILTER_MODELS = {"cbf": "kinematic", "mpsf": "dynamic"}

#: Safety-filter families a run can be wrapped in: none, the probabilistic HOCBF QP
#: (the paper's) and the predictive safety filter.
FILTER_KINDS = ("none", "cbf", "mpsf")
#: The filters ``saferace safety-table --filters`` compares: the CBF with the squared
#: slack (the paper's) or the exact L1 one, and the predictive filter.
COMPARED_FILTERS = ("cbf", "cbf-l1", "mpsf")
#: Named gain settings of the filter (the keys of ``saferace.safety.cbf.filter.GAIN_PRESETS``).
GAIN_NAMES = ("paper", "grip", "tuned", "tuned-grip")
#: How the filter treats its state's uncertainty: chance constraints on the samples' spread
#: (the paper's), or barrier conditions that hold for every state of the source's interval,
#: with a fallback where they cannot (``saferace.safety.cbf.filter.SafetyFilter``).
UNCERTAINTY_MODES = ("chance", "robust")
#: How the state network gives its uncertainty: MC dropout (the paper's), a deep ensemble
#: of heteroscedastic networks (``saferace.learning.ensemble``), a MIMO ensemble of
#: heteroscedastic subnetworks sharing one ResNet-18 (``NetworkConfig.subnetworks``), a
#: packed ensemble of independent members in grouped layers (``saferace.learning.packed``),
#: or one heteroscedastic network (its own variance: what a conformal calibration scales).
STATE_UNCERTAINTY_METHODS = ("mc-dropout", "ensemble", "mimo", "packed", "heteroscedastic")
#: Feedback an adaptive conformal interval learns from: the truth a step late (oracle
#: feedback) or the odometry's prediction (``saferace.safety.uncertainty.adaptive``).
ADAPTIVE_FEEDBACK = ("oracle", "odometry")
#: The miss rate a conformal calibration of the state network allows (its interval covers
#: the truth on at least 1 - alpha of exchangeable frames, its monitor raises on at most alpha).
CONFORMAL_ALPHA = 0.05
#: What a calibration's out-of-distribution monitor looks at: the state network's backbone
#: features (they move with a new look), its spread (which hardly did), or nothing.
OOD_MONITORS = ("features", "spread", "none")
DEFAULT_MONITOR = "features"
DEFAULT_GAINS = "grip"
#: The filter's uncertainty mode and gains (and a DAgger run's state uncertainty) left to
#: ``auto``: what keeps a user safe. A learned state source gets the robust mode over its
#: conformal interval and ``ROBUST_GAINS`` (a steeper first class-K function, saturating
#: to a stopping condition: with ``DEFAULT_GAINS`` an uncertain heading brakes the car to a
#: crawl; and the steering within the tyres' grip), and a DAgger run that feeds its filter
#: the perceived state trains a deep ensemble; anything else gets the paper's chance
#: constraints, ``DEFAULT_GAINS`` and MC dropout.
AUTO = "auto"
ROBUST_GAINS = "tuned-grip"
#: The filter QP's penalty on its slacks: the paper's squared one, or the exact L1 one
#: (``saferace.safety.cbf.exact_penalty``: the hard constraints wherever they can hold).
SQUARED_SLACK = "squared"
SLACK_PENALTIES = (SQUARED_SLACK, "l1")

#: What feeds the filter the lane state: the truth, the truth with noise, a checkpoint's
#: state network, or the generic perception model (``saferace.learning.perception``).
STATE_SOURCE_KINDS = ("oracle", "noisy", "learned", "generic")
#: The track-agnostic perception model by name: ``generic`` (its default recipe) or
#: ``generic:RECIPE``.
GENERIC_SOURCE = "generic"
#: The generic perception model's frames: mono, this many pixels high and wide.
PERCEPTION_IMAGE_SIZE = 64
#: Recipes of the generic perception model: ``default`` (what the filters use) and
#: ``quick`` (minutes: for tests and a first look).
PERCEPTION_RECIPES = ("default", "quick")
#: The lane state a DAgger run's filtered drives see: the generic perception model's, the
#: run's own state network's (the paper's) or the truth.
DAGGER_STATE_SOURCES = (GENERIC_SOURCE, "learned", "oracle")
#: The noisy oracle's default standard deviations ``(e_y_m, e_psi_rad)`` and samples.
DEFAULT_STATE_NOISE = (0.05, 0.05)
NOISY_SAMPLES = 20
#: MC-dropout samples of a learned agent or state source per step.
MC_SAMPLES = 10

#: Visual and physical domain-randomisation presets (``saferace.envs.randomization``).
RANDOMIZATION_PRESETS = ("none", "mild", "strong")
#: The looks of the shift severities 0 (the training look) .. 5 (Ovadia et al. 2019).
SHIFT_LOOKS = tuple(f"severity-{level}" for level in range(6))
#: What a smoothed lane keeps (``saferace.track.smoothing``).
SMOOTHING_KEEPS = ("widths", "boundaries")

#: Presets of the paper's tables (``saferace.experiments.paper``).
PAPER_PRESETS = ("quick", "full")

#: Radius (m) of the random tracks the experiments generate by seed.
RANDOM_TRACK_RADIUS_M = 3.0

#: The file that marks a finished collection round.
MANIFEST_FILE = "manifest.json"

#: Runs of a submission that ``saferace verify`` drives again unless told otherwise.
VERIFY_RUNS = 4

#: Where networks train and predict (``saferace.learning.device``), and the environment
#: variable that carries the command line's choice into worker processes and Ray tasks.
DEVICE_HELP = "auto (a GPU where PyTorch sees one), cpu, cuda or cuda:N"
DEVICE_VARIABLE = "SAFERACE_DEVICE"
#: Set to 0 to run networks eagerly on the CPU (``saferace.learning.cpu_compile``).
COMPILE_VARIABLE = "SAFERACE_COMPILE"
