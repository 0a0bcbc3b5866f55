"""Blender scene building (board mesh and material, lights, camera, clutter); the only package that imports bpy."""
