#!/usr/bin/env bash
# The main job on the shipped sample recording (grows with the pipeline).
set -euo pipefail
cd "$(dirname "$0")/.."
echo "demo: the pipeline is not wired yet" >&2
exit 1
