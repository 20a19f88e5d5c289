"""Mesh rendering: ray-cast z-depth, triangle ids, normals (Open3D ``RaycastingScene``).

Used by the phantom (ground truth and shading) and by the bootstrapping loop
(simulated depth of the fused mesh at every frame's pose).
"""

from endorecon.rendering.raycast import MeshRenderer, load_mesh_arrays, pixel_rays_cam, render_depth

__all__ = ["MeshRenderer", "render_depth", "load_mesh_arrays", "pixel_rays_cam"]
