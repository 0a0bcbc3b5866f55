"""A physical webcam sensor: scene luminance -> 8-bit frame, with auto-exposure and real noise.

Light reaches a pixel as photometric exposure (lux seconds at the sensor):

    H = L * t * pi / (4 N^2)          L: scene luminance (cd/m^2), t: exposure (s), N: f-number

and becomes ``H * electrons_per_lux_s`` photo-electrons on average. The frame is then

    e  = Poisson(mean electrons), clipped at the full well       (shot noise)
       + Normal(0, read_noise) per pixel + Normal(0, row_noise) per row   (read and row noise)
    v  = e * gain / full_well                                     (analogue gain, 1.0 = full scale)
    DN = round(255 * clip(v, 0, 1) ** (1 / gamma))                (response curve, 8 bits)

Auto-exposure does what a webcam does: lengthen the exposure up to the frame time, then raise
the gain up to its limit, to bring the mean level to ``target_level``. Below that light the
frame gets darker *and* noisier, with few electrons behind each pixel: a 0.3 lux frame
looks like a dark webcam frame, not like a bright frame scaled down.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np


# Luminance from linear Rec.709 RGB (Blender's scene-linear space), the sensor's spectral response.
REC709_LUMA = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)


@dataclass(frozen=True)
class SensorParams:
    """A small-pixel USB webcam (defaults) — the paper's kind of camera."""

    f_number: float = 2.0
    electrons_per_lux_s: float = 15000.0  # per pixel: QE x pixel area x lens transmission
    full_well: float = 6000.0  # electrons
    read_noise: float = 3.0  # electrons rms, per pixel
    row_noise: float = 0.8  # electrons rms, one offset per row (banding)
    gamma: float = 2.2  # response curve exponent
    target_level: float = 0.18  # auto-exposure target of the mean linear level
    min_exposure_s: float = 1e-4
    max_exposure_s: float = 1.0 / 30.0  # the frame time at 30 fps
    max_gain: float = 16.0
    noise: bool = True  # False: an ideal sensor (mean electrons, no shot/read/row noise) for label checks


@dataclass(frozen=True)
class Exposure:
    """The settings a frame was taken with, recorded per frame in the shards."""

    exposure_s: float
    gain: float


def luminance_of_paper(lux: float, reflectance: float = 0.8) -> float:
    """Luminance (cd/m^2) of matte (Lambertian) paper under ``lux`` illuminance: rho E / pi."""
    return reflectance * lux / math.pi


def electrons_per_second(luminance: np.ndarray, params: SensorParams) -> np.ndarray:
    """Mean photo-electrons per second per pixel for a (H, W) luminance image in cd/m^2."""
    return np.asarray(luminance, dtype=np.float64) * (math.pi / (4.0 * params.f_number**2)) * params.electrons_per_lux_s


def auto_exposure(luminance: np.ndarray, params: SensorParams = SensorParams()) -> Exposure:
    """Exposure time, then gain, that bring the frame's mean level to ``params.target_level``."""
    rate = float(electrons_per_second(luminance, params).mean())
    wanted = params.target_level * params.full_well  # electrons x gain
    if rate <= 0.0:
        return Exposure(params.max_exposure_s, params.max_gain)
    exposure = min(max(wanted / rate, params.min_exposure_s), params.max_exposure_s)
    gain = min(max(wanted / (rate * exposure), 1.0), params.max_gain)
    return Exposure(exposure, gain)


def auto_gain(luminance: np.ndarray, exposure_s: float, params: SensorParams = SensorParams()) -> Exposure:
    """The gain that brings the mean level to target with the exposure time already fixed
    (the renderer fixes the time first: camera shake blur depends on it)."""
    rate = float(electrons_per_second(luminance, params).mean())
    wanted = params.target_level * params.full_well
    gain = params.max_gain if rate <= 0.0 else min(max(wanted / (rate * exposure_s), 1.0), params.max_gain)
    return Exposure(float(exposure_s), float(gain))


def capture(
    luminance: np.ndarray,
    rng: np.random.Generator,
    params: SensorParams = SensorParams(),
    exposure: Exposure | None = None,
) -> tuple[np.ndarray, Exposure]:
    """Take an 8-bit frame of a (H, W) luminance image (cd/m^2, linear).

    Args:
        luminance: scene luminance reaching each pixel, e.g. a Cycles render converted to cd/m^2.
        rng: the frame's own generator; the noise is a pure function of it.
        params: the sensor.
        exposure: fixed settings, or None for auto-exposure.

    Returns:
        (H, W) uint8 frame and the exposure used.
    """
    luminance = np.asarray(luminance, dtype=np.float64)
    if luminance.ndim != 2:
        raise ValueError(f"luminance must be (H, W), got shape {luminance.shape}")
    if not np.all(np.isfinite(luminance)) or luminance.min() < 0:
        raise ValueError("luminance must be finite and >= 0 (cd/m^2)")
    exposure = exposure or auto_exposure(luminance, params)
    mean_electrons = electrons_per_second(luminance, params) * exposure.exposure_s
    if params.noise:
        electrons = np.minimum(rng.poisson(mean_electrons).astype(np.float64), params.full_well)
        electrons += rng.normal(0.0, params.read_noise, electrons.shape)
        electrons += rng.normal(0.0, params.row_noise, (electrons.shape[0], 1))
    else:
        electrons = np.minimum(mean_electrons, params.full_well)
    level = np.clip(electrons * exposure.gain / params.full_well, 0.0, 1.0)
    frame = np.round(255.0 * level ** (1.0 / params.gamma)).astype(np.uint8)
    return frame, exposure


def sensor_record(params: SensorParams, exposure: Exposure) -> dict:
    """Flat per-frame metadata: the exposure and the sensor parameters behind it."""
    return {**asdict(exposure), **{f"sensor_{k}": v for k, v in asdict(params).items()}}
