#!/usr/bin/env bash
# The packed ensemble beside the deep ensemble on the shift sweep, trained on the same frames.
#
# Both are trained on the generic perception model's rounds of its first 8 training tracks
# (build it first: saferace perception), 3 epochs with augmentation, calibrated (conformal,
# with the feature monitor) on 4 of its calibration tracks, then drive the expert behind the
# robust CBF fed each, on two random tracks neither saw (TRACK_A, TRACK_B: CSVs of
# saferace.track.random_track.write_random_tracks) at shift severities 0-5.
#
#     bash benchmarks/packed_vs_deep.sh OUT TRACK_A.csv TRACK_B.csv
set -euo pipefail
OUT=$1
TRACK_A=$2
TRACK_B=$3
ROUNDS=${SAFERACE_CACHE:-$HOME/.cache/saferace}/perception/default/rounds
TRAIN=$(for seed in $(seq 90001 90008); do echo "$ROUNDS/train_$seed"; done)
CALIBRATION=$(for seed in $(seq 91001 91004); do echo "$ROUNDS/calibration_$seed"; done)
mkdir -p "$OUT"
for method in packed ensemble; do
  if [ ! -f "$OUT/$method.pt" ]; then
    # shellcheck disable=SC2086  # the lists of round folders split into arguments
    saferace train $TRAIN --out "$OUT/${method}_raw.pt" --epochs 3 --batch-size 64 \
      --lr-schedule cosine --augment --no-validation --state-uncertainty "$method" --device cpu
    # shellcheck disable=SC2086
    saferace calibrate "$OUT/${method}_raw.pt" $CALIBRATION --out "$OUT/$method.pt" --device cpu
  fi
  saferace robustness --agent expert --task CenterLine --track "$TRACK_A" "$TRACK_B" \
    --presets severity-0 severity-1 severity-2 severity-3 severity-4 severity-5 --seeds 0 \
    --max-seconds 20 --filter cbf --state-source "learned:$OUT/$method.pt" \
    --out "$OUT/robustness_$method" --device cpu
done
saferace shift-sweep ensemble="$OUT/robustness_ensemble" packed="$OUT/robustness_packed" \
  --out "$OUT/sweep"
