#!/usr/bin/env bash
# Runs the whole test suite in .venv on its own ROS_DOMAIN_ID (so parallel runs never hear each other).
set -euo pipefail
cd "$(dirname "$0")/.."
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$(( (RANDOM % 90) + 10 ))}
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export MPLBACKEND=Agg
exec .venv/bin/python -m pytest -q -p no:cacheprovider tests "$@"
