"""Degradations change image statistics as specified and are deterministic in the seed."""
import numpy as np
import pytest
import torch

from vigs_core.sim.degrade import (
    DegradeConfig,
    degrade_image,
    motion_blur_kernel,
    select_frames,
    subframe_offsets_ns,
    to_uint8,
)

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def image():
    """A textured test image (random mosaic) in [0.1, 0.9]."""
    rng = np.random.default_rng(0)
    cells = rng.uniform(0.1, 0.9, (24, 36)).astype(np.float32)
    return np.kron(cells, np.ones((8, 8), dtype=np.float32))  # (192, 288)


def _gradient_energy(img):
    img = img.astype(np.float64)
    return np.mean(np.diff(img, axis=0) ** 2) + np.mean(np.diff(img, axis=1) ** 2)


def test_no_degradation_is_plain_quantisation(image):
    np.testing.assert_array_equal(degrade_image(image, 0, 0.0, DegradeConfig()), to_uint8(image))


def test_over_exposure_scales_and_saturates(image):
    out = degrade_image(image, 0, 0.0, DegradeConfig(over_exposure=2.0)).astype(np.float64) / 255
    np.testing.assert_allclose(out, np.minimum(1.0, 2.0 * image), atol=0.5 / 255 + 1e-6)
    assert (out >= 1.0).mean() > 0.3 and (image >= 1.0).mean() == 0


def test_low_light_gamma_and_noise_statistics(image):
    dark = degrade_image(image, 0, 0.0, DegradeConfig(low_light_gamma=2.2)).astype(np.float64) / 255
    np.testing.assert_allclose(dark, image**2.2, atol=0.5 / 255 + 1e-6)
    # shot noise: the variance of Poisson(s I) / s is I / s
    flat = np.full((400, 400), 0.25, dtype=np.float32)
    s = 200.0
    shot = degrade_image(flat, 0, 0.0, DegradeConfig(photon_scale=s)).astype(np.float64) / 255
    assert shot.mean() == pytest.approx(0.25, abs=0.003)
    assert shot.var() == pytest.approx(0.25 / s + 1 / (12 * 255**2), rel=0.05)
    read = degrade_image(flat, 0, 0.0, DegradeConfig(read_noise=6.0)).astype(np.float64)
    assert read.std() == pytest.approx(np.sqrt(6.0**2 + 1 / 12), rel=0.05)
    assert read.mean() == pytest.approx(0.25 * 255, abs=0.2)


def test_motion_blur_smooths_along_a_random_direction(image):
    config = DegradeConfig(blur_kernel=9, seed=3)
    a = degrade_image(image, 5, 0.0, config)
    assert _gradient_energy(a) < 0.6 * _gradient_energy(to_uint8(image))
    assert abs(a.astype(np.float64).mean() - to_uint8(image).astype(np.float64).mean()) < 1.5  # mean kept
    assert not np.array_equal(a, degrade_image(image, 6, 0.0, config))  # another frame, another direction
    np.testing.assert_array_equal(a, degrade_image(image, 5, 0.0, config))  # deterministic
    k = motion_blur_kernel(7, 0.3)
    assert k.sum() == pytest.approx(1.0) and (k > 0).sum() >= 7


def test_exposure_changes_over_time(image):
    config = DegradeConfig(exposure_amplitude=0.3, exposure_period_s=4.0)
    means = [degrade_image(image, k, k * 0.5, config).mean() for k in range(8)]
    base = to_uint8(image).mean()
    assert max(means) > 1.15 * base and min(means) < 0.85 * base


def test_frame_selection_stride_drops_and_subframes():
    np.testing.assert_array_equal(select_frames(10, DegradeConfig(stride=3)), [0, 3, 6, 9])
    kept = select_frames(1000, DegradeConfig(drop_probability=0.2, seed=1))
    assert 740 < len(kept) < 860 and np.all(np.diff(kept) > 0)
    np.testing.assert_array_equal(kept, select_frames(1000, DegradeConfig(drop_probability=0.2, seed=1)))
    assert not np.array_equal(kept, select_frames(1000, DegradeConfig(drop_probability=0.2, seed=2)))
    offsets = subframe_offsets_ns(DegradeConfig(exposure_time_s=0.01, blur_subframes=5))
    np.testing.assert_array_equal(offsets, [-4_000_000, -2_000_000, 0, 2_000_000, 4_000_000])
    with pytest.raises(ValueError, match="stride"):
        DegradeConfig(stride=0)
