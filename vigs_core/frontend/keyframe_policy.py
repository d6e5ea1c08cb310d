"""Keyframe selection by motion (VIGS-SLAM 3.1, DROID-SLAM's motion filter).

A frame becomes a keyframe when the mean optical flow from the last keyframe exceeds ``flow_threshold_px``
or when ``max_interval_s`` has elapsed since it.

With ``translation_flow_px`` set, the flow test uses the translation-induced part of the flow instead (the flow
of the keyframe's points under the relative pose minus their flow under its rotation alone), and the total flow
only above ``max_flow_px`` (to keep overlap). Pure rotations then add no keyframes: a window of keyframes that
differ only by rotation cannot triangulate depth, and on hybrid V1_01 such a stretch made the monocular scale
jump by a third.
"""
from __future__ import annotations

from dataclasses import dataclass

from vigs_core.ranges import bounded


@dataclass
class KeyframePolicyConfig:
    """Args:
        flow_threshold_px: mean flow to the last keyframe that makes a new keyframe, pixels at the input
            resolution. The paper states 2.4 px; DROID-SLAM (which VIGS-SLAM follows) measures its 2.4 at 1/8
            resolution, i.e. 19.2 input pixels. The default 16 px sits near the latter: at 2.4 input pixels
            nearly every 20 Hz EuRoC frame would become a keyframe and the window would span too short a
            baseline to triangulate (see docs of the frontend benchmark).
        max_interval_s: a keyframe at least this often, seconds.
        translation_flow_px: threshold on the translation-induced mean flow, input pixels (None: use the total
            flow and ``flow_threshold_px``).
        max_flow_px: with ``translation_flow_px``, a keyframe also when the total mean flow exceeds this.
    """

    flow_threshold_px: float = bounded(16.0, 0)
    max_interval_s: float = bounded(3.0, 0)
    translation_flow_px: float | None = bounded(8.0, 0)
    max_flow_px: float = bounded(48.0, 0)


class KeyframePolicy:
    """Decides whether a tracked frame becomes a keyframe."""

    def __init__(self, config: KeyframePolicyConfig | None = None) -> None:
        self.config = config or KeyframePolicyConfig()

    def is_keyframe(self, mean_flow_px: float, seconds_since_keyframe: float,
                    translation_flow_px: float | None = None) -> bool:
        """True when the (translation) flow or the elapsed time exceeds its threshold (module docstring).

        ``translation_flow_px``: translation-induced mean flow, used when both it and the config's
        ``translation_flow_px`` are given.
        """
        cfg = self.config
        if seconds_since_keyframe >= cfg.max_interval_s:
            return True
        if cfg.translation_flow_px is not None and translation_flow_px is not None:
            return translation_flow_px > cfg.translation_flow_px or mean_flow_px > cfg.max_flow_px
        return mean_flow_px > cfg.flow_threshold_px
