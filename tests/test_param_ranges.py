"""Valid ranges of numeric parameters, stated once on the config fields (:func:`vigs_core.ranges.bounded`) and
checked by ``vigs run`` (load_config), ``vigs launch`` (check_params_file) and the ROS nodes (rcl + declare)."""
from __future__ import annotations

import dataclasses
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
from ros_helpers import isolated_env, ros_context as ros_context_fixture

from vigs_cli.main import main as vigs_main
from vigs_core.frontend.dis_flow import DISFlowConfig
from vigs_core.loop import LoopConfig
from vigs_core.mapping import MapperConfig
from vigs_core.ranges import Range, bounded, field_range
from vigs_core.system import load_config
from vigs_core.system.config import PipelineConfig
from vigs_core.viz.rerun_log import RerunConfig
from vigs_ros.params import check_params_file, dataclass_specs, declare

ROOT = Path(__file__).resolve().parent.parent
ros_context = ros_context_fixture   # the fixture, for pytest to find under its name


def frontend_yaml(path: Path, body: str) -> Path:
    path.write_text("frontend:\n  ros__parameters:\n" + body)
    return path


def test_range_membership_and_text():
    assert 0 in Range(0, 1) and 1 in Range(0, 1) and 0.5 in Range(0, 1)
    assert -1e-9 not in Range(0, 1) and 1.0000001 not in Range(0, 1) and float("nan") not in Range(0, 1)
    assert 0 not in Range(0, None, lo_open=True) and 1e-300 in Range(0, None, lo_open=True)
    assert 10 ** 9 in Range(1) and -5 in Range(None, 3)
    assert [str(r) for r in (Range(0, 1), Range(1), Range(0, lo_open=True), Range(None, 3))] == \
        ["[0, 1]", "[1, inf)", "(0, inf)", "(-inf, 3]"]
    with pytest.raises(ValueError, match=r"default 2 outside its range \[0, 1\]"):
        bounded(2, 0, 1)
    with pytest.raises(ValueError, match=r"default 0.0 outside its range \(0, inf\)"):
        bounded(0.0, 0, lo_open=True)


def ranged_fields(obj, prefix: str = ""):
    """``(dotted name, value, range)`` of every ranged field of a config instance and its nested configs."""
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            yield from ranged_fields(value, f"{prefix}{f.name}.")
        elif field_range(f) is not None:
            yield prefix + f.name, value, field_range(f)


def test_every_default_is_within_its_range():
    """Instances, not classes: nested defaults made by factories (``BAConfig(iterations=3)``, the odometry's
    ``DISFlowConfig(finest_scale=0)``) are checked too."""
    found = {}
    for config in (PipelineConfig(), MapperConfig(), LoopConfig(), DISFlowConfig(), RerunConfig()):
        for name, value, rng in ranged_fields(config, type(config).__name__ + "."):
            assert value is None or value in rng, (name, value, str(rng))
            found[name] = rng
    assert len(found) > 100, len(found)   # the pipeline's tree holds most; the nodes' configs again
    assert str(found["PipelineConfig.odometry.min_confidence"]) == "[0, 1]"
    assert str(found["PipelineConfig.odometry.ba.iterations"]) == "[0, inf)"
    assert str(found["PipelineConfig.loop.graph.sigma_metric_log_scale"]) == "(0, inf)"
    assert str(found["RerunConfig.jpeg_quality"]) == "[1, 100]"


@pytest.mark.parametrize("body, says", [
    ("    odometry: {min_confidence: 3}\n", "parameter odometry.min_confidence: expected a value in [0, 1], got 3.0"),
    ("    odometry: {ba: {iterations: -1}}\n", "parameter odometry.ba.iterations: expected a value in [0, inf), got -1"),
    ("    imu: {gravity: 0}\n", "parameter imu.gravity: expected a value in (0, inf), got 0.0"),
    ("    odometry: {flow: {finest_scale: -2}}\n",
     "parameter odometry.flow.finest_scale: expected a value in [0, inf), got -2"),
    ("    loop: {detection: {max_orientation_deg: 181}}\n",
     "parameter loop.detection.max_orientation_deg: expected a value in [0, 180], got 181.0"),
    ("    mapping: {mapper: {render_scale: .nan}}\n", "parameter mapping.mapper.render_scale: expected a value in (0, 1]"),
])
def test_vigs_run_params_out_of_range_name_file_key_and_range(tmp_path, capsys, body, says):
    """load_config's ValueError, and ``vigs run``'s one line from it (exit 2, before the input is read)."""
    path = frontend_yaml(tmp_path / "params.yaml", body)
    with pytest.raises(ValueError) as err:
        load_config(path)
    assert str(err.value).startswith(f"{path}: {says}"), str(err.value)
    assert vigs_main(["run", str(tmp_path), "--params", str(path), "--no-progress"]) == 2
    out = capsys.readouterr().err
    assert out.startswith(f"vigs run: bad --params: {path}: {says}") and out.count("\n") == 1, out


def test_vigs_run_params_accept_the_boundaries(tmp_path):
    path = frontend_yaml(tmp_path / "params.yaml", "    max_frames: null\n    odometry:\n      min_confidence: 1\n"
                         "      init_min_inliers: 0\n      ba: {iterations: 0}\n"
                         "    loop: {detection: {max_orientation_deg: 180}}\n    mapping: {mapper: {render_scale: 0.5}}\n"
                         "    rerun: {jpeg_quality: 100}\n")
    cfg = load_config(path)
    assert cfg.max_frames is None
    assert (cfg.odometry.min_confidence, cfg.odometry.init_min_inliers, cfg.odometry.ba.iterations) == (1.0, 0.0, 0)
    assert (cfg.loop.detection.max_orientation_deg, cfg.mapping.mapper.render_scale) == (180.0, 0.5)
    assert cfg.rerun.jpeg_quality == 100


def test_dataclass_specs_carry_the_field_ranges():
    specs = {s.name: s for s in dataclass_specs(PipelineConfig, skip=("loop", "rerun"))}
    assert specs["odometry.min_confidence"].range == Range(0, 1)
    assert specs["odometry.graph.window"].range == Range(2)
    assert specs["imu.gravity"].range == Range(0, lo_open=True)
    assert specs["mapping.mapper.seed"].range is None            # a number without a stated range
    assert specs["odometry.solver_dtype"].range is None          # not a number
    assert specs["imu.enabled"].range is None                    # a bool
    assert specs["odometry.flow.finest_scale"].range == Range(0)  # an Optional int declared with its default


def test_vigs_launch_params_out_of_range_are_one_line_errors(tmp_path):
    """check_params_file names file, node, key, range and value; ``vigs launch`` prints that one line and exits 2
    before any node starts."""
    from vigs_ros.graph import node_params

    specs = node_params()
    ok = frontend_yaml(tmp_path / "ok.yaml", "    odometry: {min_confidence: 1}\n    imu: {max_speed: 5}\n")
    check_params_file(ok, specs)
    bad = frontend_yaml(tmp_path / "bad.yaml", "    odometry: {min_confidence: 3}\n")
    says = "parameter 'odometry.min_confidence' of frontend: expected a value in [0, 1], got 3.0"
    with pytest.raises(ValueError) as err:
        check_params_file(bad, specs)
    assert str(err.value) == f"{bad}: {says}"
    every = tmp_path / "every.yaml"
    every.write_text("/**:\n  ros__parameters:\n    mapper: {iterations: -3}\n")
    with pytest.raises(ValueError, match=re.escape("parameter 'mapper.iterations' of /**: expected a value in "
                                                   "[0, inf), got -3")):
        check_params_file(every, specs)
    done = subprocess.run([sys.executable, "-m", "vigs_cli.main", "launch", "--params", str(bad)], cwd=ROOT,
                          env=isolated_env(), capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stdout + done.stderr
    assert done.stdout.strip() == f"[launch] error: bad --params: {bad}: {says}", done.stdout


@dataclass
class Ranged:
    """Args:
        conf: a confidence.
        iters: an iteration count.
        sigma: a standard deviation.
        free: no range.
    """

    conf: float = bounded(0.5, 0, 1)
    iters: int = bounded(3, 0)
    sigma: float = bounded(1.0, 0, lo_open=True)
    free: float = 2.0


def test_node_declares_the_range_and_refuses_values_out_of_it(ros_context, tmp_path):
    """The descriptor carries a range of the value's type (rcl then refuses an out-of-range set); an override
    out of range stops declare() with a ValueError naming node, parameter, range and value, including the cases
    rclpy does not check: an int for a dynamically typed float parameter, and the open end of a range."""
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    specs = dataclass_specs(Ranged)

    def node_with(name: str, params: str) -> Node:
        f = tmp_path / f"{name}.yaml"
        f.write_text(f"/**:\n  ros__parameters:\n{params}")
        return Node(name, context=ros_context, cli_args=["--ros-args", "--params-file", str(f)])

    node = node_with("ranged_ok", "    conf: 1\n    iters: 0\n    sigma: 0.25\n    free: -7.0\n")
    try:
        assert declare(node, specs) == {"conf": 1, "iters": 0, "sigma": 0.25, "free": -7.0}
        conf, iters, sigma, free = (node.describe_parameter(n) for n in ("conf", "iters", "sigma", "free"))
        assert conf.description == "a confidence." and conf.dynamic_typing
        assert [(r.from_value, r.to_value, r.step) for r in conf.floating_point_range] == [(0.0, 1.0, 0.0)]
        assert not conf.integer_range
        assert [(r.from_value, r.to_value, r.step) for r in iters.integer_range] == [(0, 2 ** 63 - 1, 1)]
        assert not iters.floating_point_range
        assert [(r.from_value, r.to_value) for r in sigma.floating_point_range] == [(0.0, float("inf"))]
        assert not free.floating_point_range and not free.integer_range
        refused, accepted = node.set_parameters([Parameter("conf", value=3.0), Parameter("iters", value=2)])
        assert not refused.successful and "out of range" in refused.reason, refused
        assert accepted.successful and node.get_parameter("conf").value == 1
    finally:
        node.destroy_node()
    for k, (params, says) in enumerate([
            ("    conf: 3\n", "parameter conf: expected a value in [0, 1], got 3"),     # int: rclpy skips the range
            ("    conf: 1.5\n", "parameter conf: expected a value in [0, 1], got 1.5"),
            ("    iters: -1\n", "parameter iters: expected a value in [0, inf), got -1"),
            ("    sigma: 0.0\n", "parameter sigma: expected a value in (0, inf), got 0.0")]):
        node = node_with(f"ranged_bad{k}", params)
        try:
            with pytest.raises(ValueError) as err:
                declare(node, specs)
            assert str(err.value) == f"node ranged_bad{k}: {says}"
        finally:
            node.destroy_node()
