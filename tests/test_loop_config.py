"""Loop-closure settings: the paper's defaults, and the ``loop`` section of the pipeline's YAML parameters."""
import pytest

from vigs_core.loop import LoopConfig
from vigs_core.system import load_config


def test_defaults_are_the_papers_values():
    cfg = LoopConfig()
    assert cfg.enabled
    assert cfg.detection.min_keyframe_gap == 55
    assert cfg.detection.max_mean_flow_px == 22.0
    assert cfg.detection.max_orientation_deg == 120.0


def test_pipeline_yaml_overrides_loop_settings(tmp_path):
    path = tmp_path / "params.yaml"
    path.write_text("frontend:\n  ros__parameters:\n    loop:\n      enabled: false\n"
                    "      detection:\n        min_keyframe_gap: 40\n      verification:\n        inlier_px: 3.0\n")
    cfg = load_config(path)
    assert not cfg.loop.enabled
    assert cfg.loop.detection.min_keyframe_gap == 40
    assert cfg.loop.verification.inlier_px == 3.0
    assert cfg.loop.detection.max_mean_flow_px == 22.0   # untouched keys keep their defaults
    path.write_text("frontend:\n  ros__parameters:\n    loop:\n      detection:\n        gap: 40\n")
    with pytest.raises(ValueError, match=r"params.yaml: unknown parameter loop.detection.'gap'.*min_keyframe_gap"):
        load_config(path)
