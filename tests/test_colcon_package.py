"""The checkout as a ROS 2 workspace package, built by colcon from PyPI (``tools/colcon_venv``, installed by
scripts/setup.sh) the way a ROS user builds it: both packages found (``vigs_ros`` at the root, ``vigs_msgs``
under ``interfaces/``, given as base paths: colcon does not look inside a package), built, the node executables
in ``lib/vigs_ros`` where ``ros2 run`` looks them up through the ament index, a node started from the install,
and the installed launch file the one ``vigs launch`` reads."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from vigs_ros.graph import NODES
from vigs_ros.launch_file import LAUNCH_FILE, read_launch_file

ROOT = Path(__file__).resolve().parent.parent
COLCON = ROOT / "tools" / "colcon_venv" / "bin" / "colcon"


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    ws = tmp_path_factory.mktemp("ws")
    (ws / "src").mkdir()
    (ws / "src" / "vigs_ros").symlink_to(ROOT)
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}",
           "AMENT_PREFIX_PATH": sys.prefix, "CMAKE_PREFIX_PATH": sys.prefix}
    paths = ["--base-paths", "src/vigs_ros", "src/vigs_ros/interfaces/vigs_msgs"]
    listed = subprocess.run([str(COLCON), "list", "--names-only", *paths], cwd=ws, env=env, capture_output=True,
                            text=True, timeout=120)
    build = subprocess.run([str(COLCON), "build", *paths], cwd=ws, env=env, capture_output=True, text=True,
                           timeout=600)
    return ws, env, listed, build


def test_colcon_finds_and_builds_both_packages(workspace):
    ws, _, listed, build = workspace
    assert sorted(listed.stdout.split()) == ["vigs_msgs", "vigs_ros"], listed.stdout + listed.stderr
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    assert "2 packages finished" in build.stdout


def test_node_executables_are_where_ros2_run_looks(workspace):
    """``ros2 run vigs_ros <exec>``: the package prefix from the ament index, then ``lib/vigs_ros/<exec>``."""
    ws, env, _, _ = workspace
    prefix = subprocess.run(
        [sys.executable, "-c", "from ament_index_python.packages import get_package_prefix as p; print(p('vigs_ros'))"],
        env={**env, "AMENT_PREFIX_PATH": f"{ws / 'install' / 'vigs_ros'}:{ws / 'install' / 'vigs_msgs'}"},
        capture_output=True, text=True, timeout=60)
    assert prefix.stdout.strip() == str(ws / "install" / "vigs_ros"), prefix.stderr
    for name in NODES:
        exe = ws / "install" / "vigs_ros" / "lib" / "vigs_ros" / f"vigs_{name}"
        assert exe.is_file() and os.access(exe, os.X_OK), exe


def test_a_node_runs_from_the_install(workspace):
    """The IMU node started from ``lib/vigs_ros`` with the workspace sourced comes up (it reports that no IMU
    arrives, ``no_imu_error_s`` after its start) and stops cleanly on SIGINT."""
    ws, env, _, _ = workspace
    script = (f"source {ws / 'install' / 'setup.bash'} && "
              f"exec {ws / 'install' / 'vigs_ros' / 'lib' / 'vigs_ros' / 'vigs_imu_preintegration'}")
    node = subprocess.Popen(["bash", "-c", script], env={**env, "ROS_DOMAIN_ID": os.environ.get("ROS_DOMAIN_ID", "0")},
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(node.stdout), daemon=True)
    reader.start()
    deadline = time.monotonic() + 90   # imports and start-up take seconds on a loaded 2-core machine
    while time.monotonic() < deadline and node.poll() is None and not any("no IMU" in ln for ln in lines):
        time.sleep(0.2)
    os.killpg(node.pid, signal.SIGINT)
    node.wait(timeout=30)
    reader.join(timeout=10)
    out = "".join(lines)
    assert "no IMU messages received" in out and "Traceback" not in out, out
    assert node.returncode == 0, out


def test_the_installed_launch_file_is_the_one_vigs_launch_reads(workspace):
    ws, _, _, _ = workspace
    installed = ws / "install" / "vigs_ros" / "share" / "vigs_ros" / "launch" / "vigs.launch.xml"
    assert installed.read_text() == LAUNCH_FILE.read_text()
    nodes = read_launch_file(installed)
    assert [n.name for n in nodes] == list(NODES)
    for node in nodes:
        assert (ws / "install" / "vigs_ros" / "lib" / "vigs_ros" / node.exec).is_file()
        for f in node.params:
            assert (ws / "install" / "vigs_ros" / "share" / "vigs_ros" / "params" / f.name).read_text() == f.read_text()
