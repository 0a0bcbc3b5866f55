"""Scene reset, Cycles settings, and getting linear radiance out of a render."""

from __future__ import annotations

import os
from pathlib import Path

import bpy
import numpy as np

from deepcharuco.core.errors import DeepCharucoError


def reset() -> bpy.types.Scene:
    """An empty scene: every frame is built from scratch, so nothing leaks between frames."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    # Camera shake keys are a straight path over the shutter, not an eased curve.
    bpy.context.preferences.edit.keyframe_new_interpolation_type = "LINEAR"
    return bpy.context.scene


def enable_gpu() -> str:
    """Switch Cycles to the best GPU backend present; raises DeepCharucoError when there is none."""
    cycles = bpy.context.preferences.addons["cycles"].preferences
    for backend in ("OPTIX", "CUDA", "HIP", "ONEAPI", "METAL"):
        try:
            cycles.compute_device_type = backend
        except TypeError:
            continue
        cycles.get_devices()
        devices = [d for d in cycles.devices if d.type == backend]
        if devices:
            for device in cycles.devices:
                device.use = device.type == backend
            return backend
    raise DeepCharucoError("--device gpu: Cycles finds no CUDA/OptiX/HIP/oneAPI/Metal GPU here; use --device cpu")


def configure_cycles(scene: bpy.types.Scene, width: int, height: int, pixel_aspect: tuple[float, float],
                     samples: int, seed: int, threads: int, device: str, denoise: bool = False) -> None:
    """Cycles set for speed and repeatability: few samples, capped bounces, fixed seed, and no denoiser
    unless ``denoise`` (OpenImageDenoise guided by albedo and normal passes)."""
    scene.render.engine = "CYCLES"
    scene.render.resolution_x, scene.render.resolution_y = int(width), int(height)
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = pixel_aspect
    scene.render.threads_mode = "FIXED"
    scene.render.threads = max(1, int(threads))
    scene.render.film_transparent = False
    cycles = scene.cycles
    cycles.device = "GPU" if device == "gpu" else "CPU"
    if device == "gpu":
        enable_gpu()
    cycles.samples = int(samples)
    cycles.use_adaptive_sampling = True
    cycles.adaptive_threshold = 0.02
    cycles.use_denoising = bool(denoise)  # off for training frames: the sensor model adds the noise that matters
    if denoise:
        # For a render that many frames share (evaluate.paper.sequences): its Monte Carlo noise would be
        # frozen into all of them. Guided by the albedo pass, which carries the board's print, OIDN
        # keeps corners sharp: 16 spp + OIDN labels as well as 64 spp without (measured there).
        cycles.denoiser = "OPENIMAGEDENOISE"
        cycles.denoising_input_passes = "RGB_ALBEDO_NORMAL"
        cycles.denoising_prefilter = "ACCURATE"
    cycles.seed = int(seed)
    cycles.use_animated_seed = False
    # Measured at 320x240 on 2 cores: deep bounces cost time and change little in a webcam-sized
    # image of a board; the light tree costs ~15 % but without it multi-lamp scenes are salt noise.
    cycles.use_light_tree = True
    cycles.max_bounces = 2
    cycles.diffuse_bounces = 1
    cycles.glossy_bounces = 1
    cycles.transmission_bounces = 0
    cycles.volume_bounces = 0
    cycles.transparent_max_bounces = 2
    cycles.caustics_reflective = False
    cycles.caustics_refractive = False
    cycles.blur_glossy = 1.0  # fireflies from glossy paths would read as salt noise at 4 spp
    settings = scene.render.image_settings
    settings.file_format = "OPEN_EXR"
    settings.color_depth = "32"
    settings.color_mode = "RGB"
    settings.exr_codec = "NONE"


def _scratch_dir() -> Path:
    shm = Path("/dev/shm")
    return shm if shm.is_dir() and os.access(shm, os.W_OK) else Path(os.environ.get("TMPDIR", "/tmp"))


def render_radiance(scene: bpy.types.Scene) -> np.ndarray:
    """Render and return (H, W, 3) float32 linear scene radiance, row 0 at the top."""
    path = _scratch_dir() / f"deepcharuco-{os.getpid()}.exr"
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    image = bpy.data.images.load(str(path))
    try:
        width, height = image.size
        pixels = np.empty(width * height * 4, dtype=np.float32)
        image.pixels.foreach_get(pixels)
    finally:
        bpy.data.images.remove(image)
        path.unlink(missing_ok=True)
    return np.ascontiguousarray(pixels.reshape(height, width, 4)[::-1, :, :3])
