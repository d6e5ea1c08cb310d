#!/usr/bin/env bash
# Builds the in-repo rosidl interface packages (interfaces/vigs_msgs, and interfaces/tf2_msgs when no
# tf2_msgs is importable) and installs them into the venv prefix, where rclpy finds them with no extra
# environment. Idempotent: a stamp holding a hash of interfaces/ and this script skips everything when
# the packages are built and import.
#
# What the ROS 2 wheels need for this (docs: shared ros_on_pip notes, reproduced in README):
#  1. the build wheels of requirements/build.txt (rosidl generators, ament_cmake), installed by setup.sh;
#  2. the wheels' *Export.cmake files hard-code the Python and numpy include dirs of the machine that built
#     them: rewrite those to this venv's (configure fails otherwise);
#  3. AMENT_PREFIX_PATH / CMAKE_PREFIX_PATH = venv prefix; plain cmake configure, build, install.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)
VENV=${VENV:-$ROOT/.venv}
PY="$VENV/bin/python"
BUILD="$ROOT/build/interfaces"
STAMP="$VENV/.vigs-interfaces"
hash=$(find interfaces scripts/build_interfaces.sh -type f | sort | xargs cat | sha256sum | cut -d' ' -f1)

if [[ -f "$STAMP" && "$(cat "$STAMP")" == "$hash" ]] && "$PY" -c 'import vigs_msgs.msg, tf2_msgs.msg' 2>/dev/null; then
  exit 0
fi

packages=(vigs_msgs)
if ! "$PY" -c 'import tf2_msgs.msg' 2>/dev/null || [[ -f "$VENV/share/tf2_msgs/.vigs-built" ]]; then
  packages=(tf2_msgs vigs_msgs)
fi

echo "[interfaces] rewriting hard-coded include dirs in the wheels' *Export.cmake files"
"$PY" - "$VENV" <<'PYEOF'
import pathlib, re, sys, sysconfig
import numpy
venv = pathlib.Path(sys.argv[1])
py_inc = sysconfig.get_paths()["include"]
np_inc = numpy.get_include()
# Any python3.X include dir or numpy include dir that does not exist here is one of the wheel builder's.
pattern = re.compile(r'[^";]*/include/python3\.\d+|[^";]*/site-packages/numpy/(?:_core|core)/include')
for path in (venv / "share").glob("**/*Export.cmake"):
    text = path.read_text()
    def fix(m):
        s = m.group(0)
        if pathlib.Path(s).exists():
            return s
        return np_inc if "numpy" in s else py_inc
    new = pattern.sub(fix, text)
    if new != text:
        path.write_text(new)
PYEOF

export AMENT_PREFIX_PATH="$VENV"
export CMAKE_PREFIX_PATH="$VENV"
export PATH="$VENV/bin:$PATH"
for pkg in "${packages[@]}"; do
  echo "[interfaces] building $pkg"
  mkdir -p "$BUILD/$pkg"
  cmake -S "interfaces/$pkg" -B "$BUILD/$pkg" -DCMAKE_INSTALL_PREFIX="$VENV" \
    -DPython3_EXECUTABLE="$PY" -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release > "$BUILD/$pkg.log" 2>&1 \
    || { cat "$BUILD/$pkg.log"; echo "[interfaces] cmake configure of $pkg failed" >&2; exit 1; }
  cmake --build "$BUILD/$pkg" -j "$(nproc)" >> "$BUILD/$pkg.log" 2>&1 \
    || { tail -50 "$BUILD/$pkg.log"; echo "[interfaces] build of $pkg failed" >&2; exit 1; }
  cmake --install "$BUILD/$pkg" >> "$BUILD/$pkg.log" 2>&1 \
    || { tail -50 "$BUILD/$pkg.log"; echo "[interfaces] install of $pkg failed" >&2; exit 1; }
  [[ "$pkg" == tf2_msgs ]] && touch "$VENV/share/tf2_msgs/.vigs-built"
done

"$PY" -c 'import vigs_msgs.msg, tf2_msgs.msg' \
  || { echo "[interfaces] built, but vigs_msgs / tf2_msgs do not import from $PY" >&2; exit 1; }
echo "$hash" > "$STAMP"
echo "[interfaces] installed into $VENV: ${packages[*]}"
