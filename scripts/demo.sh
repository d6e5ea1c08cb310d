#!/usr/bin/env bash
# The main job (`make demo`): the VIGS ROS 2 node graph on the shipped sample recording.
#
# `vigs launch` starts the four nodes (imu_preintegration, frontend, mapper, loop_detector) as separate
# processes on an isolated ROS domain, replays bags/v1_01_easy_hybrid_376x240 into them as fast as the frontend
# consumes (--fast: one image per acknowledged frame, so no frame is dropped), and shuts the graph down at
# the end. At shutdown the frontend writes the final trajectory of every frame (TUM body poses, like
# `vigs run`'s trajectory.txt), the causal odometry, the keyframes and a frame count report; the mapper
# writes the Gaussian map (3DGS PLY). Then `vigs eval` scores the trajectory against the ground truth and plots it
# (report.html, with the frontend node's frontend_report.json beside the trajectory: timings, scale and biases).
#
# Environment: VIGS_DEMO_OUT (output folder, default out/demo), ROS_DOMAIN_ID (default: 10 + pid % 91).
set -euo pipefail
cd "$(dirname "$0")/.."

BAG=bags/v1_01_easy_hybrid_376x240
GT=${BAG}_groundtruth_tum.txt
OUT=${VIGS_DEMO_OUT:-out/demo}
VIGS=.venv/bin/vigs
PY=.venv/bin/python

export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$(( 10 + $$ % 91 ))}  # isolated from other graphs on this machine
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
unset ROS_LOCALHOST_ONLY

rm -rf "$OUT"
mkdir -p "$OUT"
cat > "$OUT/demo_params.yaml" <<EOF
# written by scripts/demo.sh: where the nodes save their outputs at shutdown
frontend:
  ros__parameters:
    output_dir: $OUT
mapper:
  ros__parameters:
    map_path: $OUT/map.ply
    shutdown_drain_s: 20.0    # the mapper lags the frontend: apply more of its queue before saving
EOF

echo "== vigs launch --bag $BAG --fast (4 node processes + replay; log: $OUT/launch.log)"
start=$(date +%s)
if ! "$VIGS" launch --bag "$BAG" --fast --params "$OUT/demo_params.yaml" > "$OUT/launch.log" 2>&1; then
    tail -n 40 "$OUT/launch.log" >&2
    echo "demo: the node graph failed (full log: $OUT/launch.log)" >&2
    exit 1
fi
grep -E '^\[(replay|launch|frontend|mapper)\]' "$OUT/launch.log" | grep -v 'started ' || true
echo "graph run: $(( $(date +%s) - start )) s"

for f in trajectory.txt keyframes.txt frontend_report.json map.ply; do
    if [ ! -s "$OUT/$f" ]; then
        echo "demo: $OUT/$f was not written (see $OUT/launch.log)" >&2
        exit 1
    fi
done

echo
echo "== frames"
"$PY" - "$OUT/frontend_report.json" <<'EOF'
import json, sys
r = json.load(open(sys.argv[1]))
dropped = r["frames_in"] - r["frames_tracked"]
init = r["inertial_initialized_at_s"]
print(f"images received {r['frames_in']}, tracked {r['frames_tracked']}, posed {r['frames_posed']}, "
      f"dropped {dropped}, keyframes {r['keyframes']}, "
      + ("IMU initialised at t = %.2f s" % init if init is not None else "IMU not initialised"))
EOF

echo
echo "== accuracy of $OUT/trajectory.txt against $GT"
echo "-- Sim(3) alignment (monocular scale free)"
"$VIGS" eval "$GT" "$OUT/trajectory.txt" --align sim3 --recall 0.05 0.10 --html "$OUT/report.html" \
    | tee "$OUT/accuracy_sim3.txt"
echo "-- SE(3) alignment (metric: no scale correction)"
"$VIGS" eval "$GT" "$OUT/trajectory.txt" --align se3 --recall 0.05 0.10 | tee "$OUT/accuracy_se3.txt"

echo
echo "== outputs in $OUT/"
echo "  trajectory.txt       every frame, final estimates (TUM, body pose in the world)"
echo "  odometry.txt         every frame as first estimated (causal; TUM)"
echo "  keyframes.txt        keyframes, final estimates (TUM)"
echo "  map.ply, map.json    Gaussian map (3DGS PLY layout) and its sidecar"
echo "  frontend_report.json frame counts (tracked, skipped), IMU initialisation, latency, node counters"
echo "  frames_processed.txt stamps of the tracked frames (vigs run --frames-from replays the run)"
echo "  accuracy_*.txt       the tables above; launch.log the graph's log"
echo "  report.html          the trajectory against the ground truth, its error over time, the keyframes (plots in"
echo "                       report_figures/; open it in a browser)"
