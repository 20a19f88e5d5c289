"""Pictures of residuals: a heat-map of the registered mesh from a few viewpoints, and a histogram.

Rendering is headless: an Open3D ``RaycastingScene`` casts one ray per pixel,
the per-vertex residual is interpolated with the hit's barycentrics, and the
colour is shaded by |n·ray| so the shape reads; matplotlib lays out the views
with a colour bar in mm.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import open3d as o3d  # noqa: E402

from endorecon.utils.io import atomic_path  # noqa: E402


def _view_directions(vertices: np.ndarray, n_views: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(viewing direction from the eye to the centre, up vector) pairs from the PCA axes of the mesh."""
    c = vertices.mean(0)
    _, _, Vt = np.linalg.svd(vertices - c, full_matrices=False)
    e0, e1, e2 = Vt  # largest to smallest extent
    dirs = [(-e2, e0), (e2, e0), (-(e1 + e2) / np.sqrt(2), e0), (-e1, e0), (-e0, e1)]
    return dirs[:n_views]


def render_scalar_views(
    mesh: o3d.geometry.TriangleMesh,
    vertex_values: np.ndarray,
    vmax: float,
    n_views: int = 3,
    width: int = 400,
    height: int = 320,
    fov_deg: float = 50.0,
    cmap: str = "turbo",
) -> list[np.ndarray]:
    """Render a mesh coloured by a per-vertex scalar.

    Args:
        mesh: triangle mesh with V vertices.
        vertex_values: (V,) scalar per vertex (clipped to [0, vmax] for colour).
    Returns:
        n_views RGB images (height, width, 3) float in [0, 1], white background.
    """
    v = np.asarray(mesh.vertices, dtype=np.float64)
    tri = np.asarray(mesh.triangles)
    if vertex_values.shape != (len(v),):
        raise ValueError(f"vertex_values must be ({len(v)},), got {vertex_values.shape}")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    centre = 0.5 * (v.min(0) + v.max(0))
    radius = float(np.linalg.norm(v - centre, axis=1).max())
    dist = 1.05 * radius / np.sin(np.deg2rad(fov_deg) / 2)
    colormap = plt.get_cmap(cmap)
    images = []
    for view_dir, up in _view_directions(v, n_views):
        eye = centre - dist * view_dir
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            fov_deg, centre.tolist(), eye.tolist(), up.tolist(), width, height
        )
        hit = scene.cast_rays(rays)
        t_hit = hit["t_hit"].numpy()
        ok = np.isfinite(t_hit)
        prim = hit["primitive_ids"].numpy()[ok].astype(np.int64)
        uv = hit["primitive_uvs"].numpy()[ok].astype(np.float64)
        vals = vertex_values[tri[prim]]  # (K, 3)
        val = (1 - uv.sum(1)) * vals[:, 0] + uv[:, 0] * vals[:, 1] + uv[:, 1] * vals[:, 2]
        ray_d = rays.numpy()[..., 3:][ok]
        ray_d /= np.linalg.norm(ray_d, axis=1, keepdims=True)
        nrm = hit["primitive_normals"].numpy()[ok]
        shade = 0.35 + 0.65 * np.abs((nrm * ray_d).sum(1))
        img = np.ones((height, width, 3))
        img[ok] = colormap(np.clip(val / vmax, 0, 1))[:, :3] * shade[:, None]
        images.append(img)
    return images


def save_residual_heatmap(
    mesh: o3d.geometry.TriangleMesh,
    vertex_residual_mm: np.ndarray,
    path: str | Path,
    vmax_mm: float | None = None,
    n_views: int = 3,
    title: str = "residual to reference",
    width: int = 400,
    height: int = 320,
) -> Path:
    """PNG of the registered mesh coloured by per-vertex residual (mm), ``n_views`` views, colour bar in mm.

    vertex_residual_mm: (V,).  vmax_mm defaults to max(1.5, 99th percentile).
    """
    if vmax_mm is None:
        vmax_mm = max(1.5, float(np.percentile(vertex_residual_mm, 99)))
    images = render_scalar_views(mesh, vertex_residual_mm, vmax_mm, n_views, width, height)
    fig, axes = plt.subplots(1, n_views, figsize=(3.6 * n_views + 0.8, 3.6 * height / width + 0.6), squeeze=False)
    for ax, img in zip(axes[0], images):
        ax.imshow(img)
        ax.set_axis_off()
    sm = plt.cm.ScalarMappable(cmap="turbo", norm=matplotlib.colors.Normalize(0, vmax_mm))
    fig.colorbar(sm, ax=axes[0].tolist(), fraction=0.025, pad=0.02, label="point-to-surface distance [mm]")
    fig.suptitle(title)
    return _save(fig, path)


def save_residual_histogram(residual_mm: np.ndarray, path: str | Path, title: str = "residual histogram") -> Path:
    """PNG histogram of residuals (mm) with mean / median / p95 marked.  residual_mm: (N,)."""
    r = np.asarray(residual_mm, dtype=np.float64)
    fig, ax = plt.subplots(figsize=(6, 4))
    hi = max(float(np.percentile(r, 99.5)), 1e-6)
    clipped = r > hi
    # The far tail goes into the last bin so the body of the distribution stays readable.
    label = f"last bin: {clipped.sum()} points > {hi:.3f} mm" if clipped.any() else None
    ax.hist(np.clip(r, 0, hi), bins=80, range=(0, hi), color="0.55", label=label)
    for val, name, col in [(r.mean(), "mean", "C0"), (np.median(r), "median", "C2"), (np.percentile(r, 95), "p95", "C3")]:
        ax.axvline(val, color=col, lw=1.5, label=f"{name} {val:.3f} mm")
    if hi >= 1.0:
        ax.axvline(1.0, color="k", ls=":", lw=1, label=f"< 1 mm: {100 * (r < 1).mean():.1f} %")
    ax.set_xlabel("point-to-surface distance [mm]")
    ax.set_ylabel("points")
    ax.set_title(f"{title} (n = {len(r)}, max {r.max():.3f} mm)")
    ax.legend()
    return _save(fig, path)


def _save(fig, path: str | Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return Path(path)
