#!/usr/bin/env bash
# Creates or refreshes .venv at the repository root and installs everything VIGS-ROS needs.
#
# The venv is refreshed when it is missing or stale: the stamp .venv/.vigs-setup holds a hash of the
# requirement files, setup.py, package.xml, the interface packages and the set-up scripts; when it
# matches, set-up does nothing, so re-running is fast. Chromium (an OS package the tests use) is installed with
# apt-get when it is missing, whatever the stamp.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)
VENV="$ROOT/.venv"
PY=${PYTHON:-python3}
STAMP="$VENV/.vigs-setup"
hash=$(cat requirements/*.txt setup.py package.xml scripts/setup.sh scripts/build_interfaces.sh \
  tools/splat_transform/package*.json $(find interfaces -type f | sort) | sha256sum | cut -d' ' -f1)

# Chromium from the OS packages: the tests open report.html in it, headless. A system package, not in the venv, so
# looked for on every run (cheap) rather than through the stamp, and installed only when missing.
if ! command -v chromium >/dev/null 2>&1; then
  as_root=()
  [[ $(id -u) -eq 0 ]] || as_root=(sudo -n)
  if [[ $(id -u) -ne 0 ]] && ! sudo -n true 2>/dev/null; then
    echo "[setup] warning: chromium is missing and installing OS packages needs root: run" \
      "'sudo apt-get install chromium' (tests/test_report_html.py opens report.html in it)" >&2
  else
    echo "[setup] chromium is missing: installing it from the OS packages (apt-get; the tests open report.html in it)"
    "${as_root[@]}" apt-get update -qq
    "${as_root[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium
  fi
fi

if [[ -x "$VENV/bin/python" && -f "$STAMP" && "$(cat "$STAMP")" == "$hash" ]]; then
  exit 0
fi
if [[ ! -x "$VENV/bin/python" ]] || ! "$VENV/bin/python" -c 'import sys' >/dev/null 2>&1; then
  echo "[setup] creating $VENV"
  rm -rf "$VENV"
  "$PY" -m venv "$VENV"
fi
echo "[setup] installing pinned dependencies (torch 2.13.0 CPU via requirements/constraints.txt)"
"$VENV/bin/python" -m pip install --quiet --upgrade pip
"$VENV/bin/python" -m pip install --quiet -c requirements/constraints.txt \
  -r requirements/runtime.txt -r requirements/test.txt -r requirements/build.txt
bash scripts/build_interfaces.sh
echo "[setup] installing PlayCanvas splat-transform from npm (a 3DGS PLY reader the tests load map.ply with)"
(cd tools/splat_transform && npm ci --no-audit --no-fund --ignore-scripts --loglevel=error)
echo "[setup] installing colcon from PyPI into tools/colcon_venv (the tests build the package with it)"
"$PY" -m venv tools/colcon_venv
tools/colcon_venv/bin/python -m pip install --quiet colcon-common-extensions==0.3.0
echo "[setup] installing the project (editable)"
"$VENV/bin/python" -m pip install --quiet --no-deps --no-build-isolation -e .
echo "$hash" > "$STAMP"
echo "[setup] done: $VENV"
