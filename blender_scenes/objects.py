"""Scene objects from a `datagen.scene.SceneSpec`: board, shapes, lamps, world, camera.

Each function turns one part of the description into Blender data and takes no decisions of
its own: all randomness was spent when the spec was sampled.
"""

from __future__ import annotations

import hashlib
import math
from functools import lru_cache
from pathlib import Path

import bpy  # first: bmesh and mathutils load with it
import bmesh
import numpy as np
from mathutils import Matrix

from blender_scenes.conversions import blender_camera_from_K, blender_camera_matrix
from blender_scenes.textures import board_texture, distractor_texture, poster_texture
from datagen.scene import BoardLook, Distractor, Light, SceneSpec, Shape, Surface, World, bend_profile
from datagen.sensor import REC709_LUMA
from deepcharuco.boards.board import BoardSpec

HDRI_DIR = Path(bpy.utils.system_resource("DATAFILES")) / "studiolights" / "world"


def _matrix(array: np.ndarray) -> Matrix:
    return Matrix([list(map(float, row)) for row in np.asarray(array)])


_RGBA_CACHE: dict[bytes, np.ndarray] = {}


def _rgba_rows_up(pixels: np.ndarray) -> np.ndarray:
    """Flat float32 RGBA, bottom row first (Blender's image origin), cached by content."""
    key = hashlib.blake2b(pixels.tobytes(), digest_size=16, person=str(pixels.shape).encode()[:16]).digest()
    if key not in _RGBA_CACHE:
        if len(_RGBA_CACHE) > 48:
            _RGBA_CACHE.clear()
        rgb = np.repeat(pixels[:, :, None], 3, axis=2) if pixels.ndim == 2 else pixels
        rgba = np.ones((*rgb.shape[:2], 4), dtype=np.float32)
        rgba[:, :, :3] = rgb[::-1] / np.float32(255.0)
        _RGBA_CACHE[key] = rgba.ravel()
    return _RGBA_CACHE[key]


def image_from_array(name: str, pixels: np.ndarray, colorspace: str) -> bpy.types.Image:
    """A Blender image from (H, W) or (H, W, 3) uint8, row 0 at the top. Kept in memory only:
    Cycles reads generated images from their buffer, no file involved."""
    height, width = pixels.shape[:2]
    image = bpy.data.images.new(name, width, height, alpha=False)
    image.colorspace_settings.name = colorspace
    image.pixels.foreach_set(_rgba_rows_up(pixels))
    return image


def _node(tree: bpy.types.NodeTree, kind: str, **inputs):
    node = tree.nodes.new(kind)
    for name, value in inputs.items():
        node.inputs[name].default_value = value
    return node


def _principled(material: bpy.types.Material):
    tree = material.node_tree
    bsdf = tree.nodes.get("Principled BSDF") or _node(tree, "ShaderNodeBsdfPrincipled")
    output = tree.nodes.get("Material Output") or _node(tree, "ShaderNodeOutputMaterial")
    tree.links.new(bsdf.outputs["BSDF"], output.inputs["Surface"])
    return tree, bsdf


def _printed_material(name: str, image: bpy.types.Image, look: BoardLook) -> bpy.types.Material:
    """Ink coverage texture (Non-Color, 1 = white) -> albedo between look.black and look.white, or
    for a monitor -> emission, under a glossy screen."""
    material = bpy.data.materials.new(name)
    tree, bsdf = _principled(material)
    texture = tree.nodes.new("ShaderNodeTexImage")
    texture.image = image
    texture.interpolation = "Linear"
    texture.extension = "EXTEND"
    bsdf.inputs["Roughness"].default_value = look.roughness
    bsdf.inputs["Specular IOR Level"].default_value = look.specular
    if look.kind == "monitor":
        bsdf.inputs["Base Color"].default_value = (look.black, look.black, look.black, 1.0)
        levels = _node(tree, "ShaderNodeMapRange", **{"To Min": 0.01, "To Max": 1.0})
        tree.links.new(texture.outputs["Color"], levels.inputs["Value"])
        tree.links.new(levels.outputs["Result"], bsdf.inputs["Emission Color"])
        bsdf.inputs["Emission Strength"].default_value = look.emission
    else:
        albedo = _node(tree, "ShaderNodeMapRange", **{"To Min": look.black, "To Max": look.white})
        tree.links.new(texture.outputs["Color"], albedo.inputs["Value"])
        tree.links.new(albedo.outputs["Result"], bsdf.inputs["Base Color"])
    return material


def _quad(name: str, x0: float, y0: float, x1: float, y1: float) -> bpy.types.Mesh:
    """A quad in its object's XY plane spanning [x0, x1] x [y0, y1], texture UV (0, 0) at (x0, y1):
    the image's top row lies at y0, as in OpenCV's board frame (Y down)."""
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([(x0, y0, 0.0), (x1, y0, 0.0), (x1, y1, 0.0), (x0, y1, 0.0)], [], [(0, 1, 2, 3)])
    uv = mesh.uv_layers.new(name="UVMap")
    for loop, coords in zip(mesh.loops, [(0.0, 1.0), (1.0, 1.0), (1.0, 0.0), (0.0, 0.0)]):
        uv.data[loop.index].uv = coords
    return mesh


def _link(name: str, data, matrix: np.ndarray) -> bpy.types.Object:
    obj = bpy.data.objects.new(name, data)
    bpy.context.scene.collection.objects.link(obj)
    obj.matrix_world = _matrix(matrix)
    return obj


def _bent_sheet(name: str, x0: float, y0: float, x1: float, y1: float, spec: SceneSpec,
                board_size_m: tuple[float, float]) -> bpy.types.Mesh:
    """`_quad`'s sheet, bent as `datagen.scene.bend_profile` says: a strip of flat pieces whose vertices
    lie at the profile's knots (and at the sheet's far edge), so the labels' ``np.interp`` of the
    profile is exactly this surface. UVs as `_quad`'s: the texture keeps its board coordinates."""
    knots, z = bend_profile(spec, board_size_m)
    low, high = (x0, x1) if spec.bend_axis == 0 else (y0, y1)
    along = np.unique(np.concatenate([[low], knots[(knots > low) & (knots < high)], [high]]))
    heights = np.interp(along, knots, z)
    vertices, faces, uvs = [], [], []
    for a, h in zip(along, heights):
        for across in ((y0, y1) if spec.bend_axis == 0 else (x0, x1)):
            x, y = (a, across) if spec.bend_axis == 0 else (across, a)
            vertices.append((float(x), float(y), float(h)))
            uvs.append(((x - x0) / (x1 - x0), 1.0 - (y - y0) / (y1 - y0)))
    for i in range(len(along) - 1):
        a0, b0, a1, b1 = 2 * i, 2 * i + 1, 2 * i + 2, 2 * i + 3
        # The winding of `_quad` (normal along the board's +Z) whichever axis the strip runs along.
        faces.append((a0, a1, b1, b0) if spec.bend_axis == 0 else (a0, b0, b1, a1))
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(vertices, [], faces)
    uv = mesh.uv_layers.new(name="UVMap")
    for loop in mesh.loops:
        uv.data[loop.index].uv = uvs[loop.vertex_index]
    return mesh


def add_board(board: BoardSpec, spec: SceneSpec) -> bpy.types.Object:
    """The target board: a quad in the board frame carrying the area-exact texture, margin included
    (a strip of quads following `bend_profile` for a bent print)."""
    texture = board_texture(board, spec.margin_m)
    width_m, height_m = texture.size_m
    x0 = y0 = -texture.margin
    if spec.bend:
        mesh = _bent_sheet("board", x0, y0, x0 + width_m, y0 + height_m, spec, board.size_m)
    else:
        mesh = _quad("board", x0, y0, x0 + width_m, y0 + height_m)
    image = image_from_array("board", texture.image, "Non-Color")
    mesh.materials.append(_printed_material("board", image, spec.board_look))
    return _link("board", mesh, spec.board_matrix)


def add_distractor(index: int, distractor: Distractor) -> bpy.types.Object:
    pixels = distractor_texture(distractor.name)
    height_m = distractor.width_m * pixels.shape[0] / pixels.shape[1]
    w, h = distractor.width_m / 2.0, height_m / 2.0
    mesh = _quad(f"distractor{index}", -w, -h, w, h)
    image = image_from_array(f"distractor{index}", pixels, "Non-Color")
    mesh.materials.append(_printed_material(f"distractor{index}", image, distractor.look))
    return _link(f"distractor{index}", mesh, distractor.matrix)


def _primitive_mesh(name: str, kind: str) -> bpy.types.Mesh:
    """Unit-sized primitives centred on the origin (a plane lies in XY)."""
    bm = bmesh.new()
    if kind == "cube":
        bmesh.ops.create_cube(bm, size=1.0, calc_uvs=True)
    elif kind == "sphere":
        bmesh.ops.create_uvsphere(bm, u_segments=24, v_segments=12, radius=0.5, calc_uvs=True)
    elif kind == "icosphere":
        bmesh.ops.create_icosphere(bm, subdivisions=1, radius=0.5, calc_uvs=True)
    elif kind in ("cylinder", "cone"):
        bmesh.ops.create_cone(bm, cap_ends=True, segments=24, radius1=0.5, radius2=0.5 if kind == "cylinder" else 0.0,
                              depth=1.0, calc_uvs=True)
    elif kind == "plane":
        bmesh.ops.create_grid(bm, x_segments=1, y_segments=1, size=0.5, calc_uvs=True)
    else:
        raise ValueError(f"unknown shape {kind!r}")
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    for polygon in mesh.polygons:
        polygon.use_smooth = kind in ("sphere", "cylinder", "cone")
    return mesh


_PATTERNS = {"noise": ("ShaderNodeTexNoise", "Fac"), "wave": ("ShaderNodeTexWave", "Fac"),
             "checker": ("ShaderNodeTexChecker", "Fac"), "brick": ("ShaderNodeTexBrick", "Fac"),
             "voronoi": ("ShaderNodeTexVoronoi", "Distance")}


def surface_material(name: str, surface: Surface) -> bpy.types.Material:
    """A Principled material coloured by a procedural pattern or a photograph."""
    material = bpy.data.materials.new(name)
    tree, bsdf = _principled(material)
    bsdf.inputs["Roughness"].default_value = surface.roughness
    coords = tree.nodes.new("ShaderNodeTexCoord")
    mapping = _node(tree, "ShaderNodeMapping")
    mapping.inputs["Scale"].default_value = (surface.scale,) * 3
    if surface.kind == "plain":
        bsdf.inputs["Base Color"].default_value = (*surface.color_a, 1.0)
    elif surface.kind == "poster":
        tree.links.new(coords.outputs["UV"], mapping.inputs["Vector"])
        mapping.inputs["Scale"].default_value = (max(1.0, surface.scale / 10.0),) * 3
        texture = tree.nodes.new("ShaderNodeTexImage")
        texture.image = bpy.data.images.get(f"poster-{surface.poster}") or image_from_array(
            f"poster-{surface.poster}", poster_texture(surface.poster), "sRGB")
        texture.extension = "REPEAT"
        tree.links.new(mapping.outputs["Vector"], texture.inputs["Vector"])
        tree.links.new(texture.outputs["Color"], bsdf.inputs["Base Color"])
    else:
        kind, output = _PATTERNS[surface.kind]
        tree.links.new(coords.outputs["Object"], mapping.inputs["Vector"])
        pattern = tree.nodes.new(kind)
        tree.links.new(mapping.outputs["Vector"], pattern.inputs["Vector"])
        ramp = tree.nodes.new("ShaderNodeValToRGB")
        ramp.color_ramp.elements[0].color = (*surface.color_a, 1.0)
        ramp.color_ramp.elements[1].color = (*surface.color_b, 1.0)
        tree.links.new(pattern.outputs[output], ramp.inputs["Fac"])
        tree.links.new(ramp.outputs["Color"], bsdf.inputs["Base Color"])
    return material


def add_shape(index: int, shape: Shape) -> bpy.types.Object:
    mesh = _primitive_mesh(f"{shape.role}{index}", shape.kind)
    mesh.materials.append(surface_material(f"{shape.role}{index}", shape.surface))
    return _link(f"{shape.role}{index}", mesh, shape.matrix)


def add_light(index: int, light: Light) -> bpy.types.Object:
    data = bpy.data.lights.new(f"lamp{index}", light.kind)
    data.energy = light.power
    data.color = light.color
    if light.kind == "AREA":
        data.size = max(light.size, 1e-3)
    elif light.kind == "SUN":
        data.angle = light.size
    else:
        data.shadow_soft_size = light.size
    if light.kind == "SPOT":
        data.spot_size = math.radians(light.spot_size_deg)
        data.spot_blend = light.spot_blend
    return _link(f"lamp{index}", data, light.matrix)


@lru_cache(maxsize=16)
def hdri_mean_radiance(name: str) -> float:
    """Mean luminance of an HDRI over the sphere (equirectangular rows weighted by cos(latitude))."""
    image = bpy.data.images.load(str(HDRI_DIR / f"{name}.exr"), check_existing=True)
    width, height = image.size
    pixels = np.empty(width * height * 4, dtype=np.float32)
    image.pixels.foreach_get(pixels)
    luminance = pixels.reshape(height, width, 4)[:, :, :3] @ REC709_LUMA
    weights = np.cos((np.arange(height) + 0.5) / height * np.pi - np.pi / 2)
    return float((luminance.mean(axis=1) * weights).sum() / weights.sum())


def light_irradiance(light: Light, point: np.ndarray) -> float:
    """Irradiance (W/m^2, Blender units) a lamp would give a surface facing it at ``point``."""
    if light.kind == "SUN":
        return light.power
    distance2 = max(float(np.sum((light.matrix[:3, 3] - point) ** 2)), 1e-6)
    return light.power / ((math.pi if light.kind == "AREA" else 4 * math.pi) * distance2)


def white_paper_radiance(spec: SceneSpec) -> float:
    """Rough radiance of white paper (albedo 1) at the board in this scene's light, or of the
    brightest emissive (monitor) board: the scale that firefly clamping is set from."""
    irradiance = math.pi * spec.world.strength * hdri_mean_radiance(spec.world.hdri)
    irradiance += sum(light_irradiance(light, spec.board_matrix[:3, 3]) for light in spec.lights)
    looks = [spec.board_look] * spec.board_present + [d.look for d in spec.distractors]
    return max([irradiance / math.pi] + [look.emission for look in looks if look.kind == "monitor"])


def set_world(world_spec: World) -> None:
    """An HDRI environment (Blender's bundled CC0 studio-light worlds), rotated about Z and scaled."""
    world = bpy.data.worlds.new("world")
    bpy.context.scene.world = world
    # The automatic importance map (2x the HDRI's size) costs ~0.9 s a frame to build; 256 is plenty.
    world.cycles.sampling_method = "MANUAL"
    world.cycles.sample_map_resolution = 256
    tree = world.node_tree
    for node in list(tree.nodes):
        tree.nodes.remove(node)
    coords = tree.nodes.new("ShaderNodeTexCoord")
    mapping = _node(tree, "ShaderNodeMapping")
    mapping.inputs["Rotation"].default_value = (0.0, 0.0, math.radians(world_spec.rotation_deg))
    environment = tree.nodes.new("ShaderNodeTexEnvironment")
    path = HDRI_DIR / f"{world_spec.hdri}.exr"
    if not path.is_file():
        raise FileNotFoundError(f"HDRI {path} is missing from this Blender install")
    environment.image = bpy.data.images.load(str(path), check_existing=True)
    background = _node(tree, "ShaderNodeBackground", Strength=world_spec.strength)
    output = tree.nodes.new("ShaderNodeOutputWorld")
    tree.links.new(coords.outputs["Generated"], mapping.inputs["Vector"])
    tree.links.new(mapping.outputs["Vector"], environment.inputs["Vector"])
    tree.links.new(environment.outputs["Color"], background.inputs["Color"])
    tree.links.new(background.outputs["Background"], output.inputs["Surface"])


def add_camera(spec: SceneSpec, frame: int = 10) -> bpy.types.Object:
    """The OpenCV camera of the spec; when shaken, keyed at frame-1, frame, frame+1 for the shutter
    start, centre and end, rendered with a centred shutter of two frames."""
    params = blender_camera_from_K(spec.K, spec.width, spec.height)
    data = bpy.data.cameras.new("camera")
    data.sensor_fit = "HORIZONTAL"
    data.sensor_width = params.sensor_width_mm
    data.lens = params.lens_mm
    data.shift_x, data.shift_y = params.shift_x, params.shift_y
    data.clip_start, data.clip_end = 0.005, 200.0
    camera = _link("camera", data, blender_camera_matrix(spec.camera_matrix))
    camera.rotation_mode = "QUATERNION"
    scene = bpy.context.scene
    scene.camera = camera
    scene.frame_set(frame)
    scene.render.use_motion_blur = spec.shaken
    if spec.shaken:
        previous = None
        for offset, pose in zip((-1, 0, 1), spec.trajectory):
            camera.matrix_world = _matrix(blender_camera_matrix(pose))
            if previous is not None and camera.rotation_quaternion.dot(previous) < 0:
                camera.rotation_quaternion = -camera.rotation_quaternion  # shortest path between keys
            previous = camera.rotation_quaternion.copy()
            camera.keyframe_insert("location", frame=frame + offset)
            camera.keyframe_insert("rotation_quaternion", frame=frame + offset)
        scene.render.motion_blur_shutter = 2.0
        scene.render.motion_blur_position = "CENTER"
        scene.frame_set(frame)
    return camera
