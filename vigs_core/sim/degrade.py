"""Image degradations and frame selection (after the VIGS-SLAM supplement's robustness study).

All functions work on float images in [0, 1] (H, W) or (H, W, 3) and are deterministic in
``(seed, frame index)``: frame ``k`` draws from ``numpy.random.default_rng([seed, 5, k])``, so a frame's
degradation does not depend on which other frames were rendered.

Order of application to a rendered frame ``I`` (sub-frame averaging happens at render time):

1. motion blur: convolution with a normalised line kernel of length ``k`` px at a random angle;
2. exposure change: ``I <- g(t) I`` with ``g(t) = 1 + A sin(2 pi t / P + phi)``;
3. over-exposure: ``I <- min(1, beta I)``;
4. low light: ``I <- I^gamma`` (gamma > 1 darkens), then shot noise ``I <- Poisson(s I) / s`` (photon
   scale ``s``: photons at full white) and read noise ``I <- I + N(0, (sigma / 255)^2)``;
5. clip to [0, 1] and quantise to 8 bits.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class DegradeConfig:
    """Degradation settings (defaults: none).

    Args:
        blur_kernel: motion-blur kernel length k (px); 0 or 1 disables it.
        exposure_time_s: exposure (s) over which sub-frame renders are averaged (centred on the stamp);
            0 renders the stamp's pose only.
        blur_subframes: number of sub-frame renders averaged when ``exposure_time_s > 0``.
        exposure_amplitude: A, relative amplitude of the exposure gain oscillation.
        exposure_period_s: P, period (s) of the exposure oscillation.
        over_exposure: beta >= 1 (1 disables it).
        low_light_gamma: gamma (1 disables it).
        photon_scale: s, photons at full white for shot noise (0 disables it).
        read_noise: sigma, Gaussian read noise in 8-bit grey levels (0 disables it).
        stride: keep every ``stride``-th frame (the IMU is kept whole).
        drop_probability: probability that a kept frame is dropped at random.
        seed: seed of all random draws.
    """

    blur_kernel: int = 0
    exposure_time_s: float = 0.0
    blur_subframes: int = 5
    exposure_amplitude: float = 0.0
    exposure_period_s: float = 8.0
    over_exposure: float = 1.0
    low_light_gamma: float = 1.0
    photon_scale: float = 0.0
    read_noise: float = 0.0
    stride: int = 1
    drop_probability: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.stride < 1:
            raise ValueError(f"DegradeConfig.stride must be >= 1, got {self.stride}")
        if not 0.0 <= self.drop_probability < 1.0:
            raise ValueError(f"DegradeConfig.drop_probability must be in [0, 1), got {self.drop_probability}")
        if self.over_exposure < 1.0 or self.low_light_gamma <= 0.0 or self.photon_scale < 0 or self.read_noise < 0:
            raise ValueError(
                "DegradeConfig: expected over_exposure >= 1, low_light_gamma > 0, photon_scale >= 0, read_noise >= 0; "
                f"got {self.over_exposure}, {self.low_light_gamma}, {self.photon_scale}, {self.read_noise}"
            )
        if self.exposure_time_s < 0 or self.blur_subframes < 1:
            raise ValueError(
                f"DegradeConfig: expected exposure_time_s >= 0 and blur_subframes >= 1, got "
                f"{self.exposure_time_s}, {self.blur_subframes}"
            )


def select_frames(n_frames: int, config: DegradeConfig) -> np.ndarray:
    """(M,) indices of the frames kept after the stride and the random drops."""
    kept = np.arange(0, n_frames, config.stride)
    if config.drop_probability > 0:
        rng = np.random.default_rng([config.seed, 6])
        kept = kept[rng.random(len(kept)) >= config.drop_probability]
    return kept


def subframe_offsets_ns(config: DegradeConfig) -> np.ndarray:
    """(S,) int64 offsets (ns) of the sub-frame renders around a frame stamp (just ``[0]`` without exposure)."""
    if config.exposure_time_s <= 0 or config.blur_subframes == 1:
        return np.zeros(1, dtype=np.int64)
    s = config.blur_subframes
    fractions = (np.arange(s) + 0.5) / s - 0.5
    return np.round(fractions * config.exposure_time_s * 1e9).astype(np.int64)


def motion_blur_kernel(length: int, angle: float) -> np.ndarray:
    """(k, k) float32 line kernel of ``length`` px at ``angle`` (rad), summing to 1 (k = length, odd-padded)."""
    size = length if length % 2 == 1 else length + 1
    kernel = np.zeros((size, size), dtype=np.float32)
    c = (size - 1) / 2
    half = (length - 1) / 2
    # sample the segment densely and splat bilinearly so every angle gives the same total weight
    for s in np.linspace(-half, half, 8 * length):
        x, y = c + s * math.cos(angle), c + s * math.sin(angle)
        x0, y0 = int(math.floor(x)), int(math.floor(y))
        fx, fy = x - x0, y - y0
        for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
            if 0 <= x0 + dx < size and 0 <= y0 + dy < size:
                kernel[y0 + dy, x0 + dx] += w
    return kernel / kernel.sum()


def degrade_image(image: np.ndarray, frame_index: int, t_s: float, config: DegradeConfig) -> np.ndarray:
    """Apply the configured degradations to one frame.

    Args:
        image: (H, W) or (H, W, 3) float32 in [0, 1].
        frame_index: index of the frame in the full (unstrided) sequence; selects its random draws.
        t_s: time of the frame (s) since the start of the sequence (exposure oscillation).
        config: degradation settings.

    Returns:
        (H, W) or (H, W, 3) uint8 image.
    """
    rng = np.random.default_rng([config.seed, 5, frame_index])
    out = image.astype(np.float32)
    if config.blur_kernel > 1:
        kernel = motion_blur_kernel(config.blur_kernel, rng.uniform(0.0, math.pi))
        out = cv2.filter2D(out, -1, kernel, borderType=cv2.BORDER_REFLECT)
    if config.exposure_amplitude != 0:
        phase = np.random.default_rng([config.seed, 7]).uniform(0, 2 * math.pi)
        gain = 1.0 + config.exposure_amplitude * math.sin(2 * math.pi * t_s / config.exposure_period_s + phase)
        out = out * np.float32(gain)
    if config.over_exposure != 1.0:
        out = np.minimum(out * np.float32(config.over_exposure), 1.0)
    if config.low_light_gamma != 1.0:
        out = np.power(np.clip(out, 0.0, 1.0), np.float32(config.low_light_gamma))
    if config.photon_scale > 0:
        out = (rng.poisson(np.clip(out, 0.0, 1.0) * config.photon_scale) / config.photon_scale).astype(np.float32)
    if config.read_noise > 0:
        out = out + rng.normal(0.0, config.read_noise / 255.0, out.shape).astype(np.float32)
    return to_uint8(out)


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Clip a [0, 1] float image and round it to uint8 grey levels."""
    return np.rint(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)
