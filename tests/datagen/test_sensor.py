import numpy as np
import pytest

from datagen.sensor import Exposure, SensorParams, auto_exposure, capture, luminance_of_paper, sensor_record

PARAMS = SensorParams()


def flat(lux: float) -> np.ndarray:
    return np.full((120, 160), luminance_of_paper(lux))


def linear_level(frame: np.ndarray) -> np.ndarray:
    return (frame.astype(np.float64) / 255.0) ** PARAMS.gamma


def test_bright_light_short_exposure_no_gain_hits_the_target():
    frame, exposure = capture(flat(700.0), np.random.default_rng(0))
    assert exposure.gain == 1.0 and exposure.exposure_s < PARAMS.max_exposure_s
    assert linear_level(frame).mean() == pytest.approx(PARAMS.target_level, rel=0.05)


def test_exposure_then_gain_then_darkness():
    settings = [auto_exposure(flat(lux)) for lux in (700.0, 30.0, 3.0, 0.3)]
    assert settings[0].exposure_s < settings[1].exposure_s == PARAMS.max_exposure_s
    assert 1.0 < settings[2].gain and settings[3].gain == PARAMS.max_gain
    dark, _ = capture(flat(0.3), np.random.default_rng(0))
    assert linear_level(dark).mean() < 0.5 * PARAMS.target_level


def test_a_dark_frame_is_noisier_than_a_bright_frame_scaled_down():
    rng = np.random.default_rng(1)
    dark, _ = capture(flat(0.3), rng)
    bright, _ = capture(flat(700.0), rng)
    scaled = linear_level(bright) * (linear_level(dark).mean() / linear_level(bright).mean())
    dark_snr = linear_level(dark).mean() / linear_level(dark).std()
    assert dark_snr < 0.25 * scaled.mean() / scaled.std()
    # Row noise: rows of a flat dark frame differ by more than pixel noise alone explains.
    assert np.var(dark.mean(axis=1)) > 1.5 * np.var(dark) / dark.shape[1]


def test_same_seed_same_bytes():
    scene = np.random.default_rng(5).uniform(0, 50, (60, 80))
    a, _ = capture(scene, np.random.default_rng(42))
    b, _ = capture(scene, np.random.default_rng(42))
    c, _ = capture(scene, np.random.default_rng(43))
    assert a.tobytes() == b.tobytes() and a.tobytes() != c.tobytes()


def test_fixed_settings_and_saturation():
    frame, exposure = capture(flat(700.0), np.random.default_rng(0), exposure=Exposure(0.1, 4.0))
    assert exposure == Exposure(0.1, 4.0) and np.all(frame == 255)
    record = sensor_record(PARAMS, exposure)
    assert record["exposure_s"] == 0.1 and record["gain"] == 4.0 and record["sensor_read_noise"] == 3.0


def test_bad_luminance():
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        capture(np.zeros((4, 4, 3)), np.random.default_rng(0))
    with pytest.raises(ValueError, match=">= 0"):
        capture(-np.ones((4, 4)), np.random.default_rng(0))
