"""Pictures of residuals: a heat-map of the registered mesh from a few viewpoints, and a histogram; and
the held-out depth error by band of relative depth.

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


def _fit_distance(radius: float, fov_deg: float, height: int, width: int) -> float:
    """Distance from the centre at which a sphere of ``radius`` fits the view whatever its orientation:
    ``fov_deg`` spans the width, so the narrower side (here the height, along which the views put the mesh's
    longest axis) sets it (sized by the width, the ends of the mesh were cut off)."""
    half = np.arctan(np.tan(np.deg2rad(fov_deg) / 2) * min(height, width) / width)
    return 1.05 * radius / np.sin(half)


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
    radius = float(np.linalg.norm(v - centre, axis=1).max()) if len(v) else 0.0
    if not np.isfinite(radius) or radius <= 1e-9 * max(1.0, float(np.abs(centre).max())):
        # A degenerate (collapsed) mesh: ray casting it can take minutes; show nothing instead.
        return [np.ones((height, width, 3)) for _ in range(n_views)]
    dist = _fit_distance(radius, fov_deg, height, width)
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

    vertex_residual_mm: (V,).  vmax_mm defaults to max(1.5, 99th percentile); vertices above it are drawn in the
    top colour, which the colour bar (an arrow) and the title (how many, up to what) say.
    """
    v = np.asarray(vertex_residual_mm, dtype=np.float64)
    if vmax_mm is None:
        vmax_mm = max(1.5, float(np.percentile(v, 99)))
    above = v > vmax_mm
    if above.any():
        title += (f"\ncolour clipped at {vmax_mm:.2f} mm: {int(above.sum())} of {len(v)} vertices above, "
                  f"up to {float(v.max()):.3f} mm")
    images = render_scalar_views(mesh, vertex_residual_mm, vmax_mm, n_views, width, height)
    fig, axes = plt.subplots(1, n_views, figsize=(3.6 * n_views + 0.8, 3.6 * height / width + 0.6), squeeze=False)
    for ax, img in zip(axes[0], images):
        ax.imshow(img)
        ax.set_axis_off()
    sm = plt.cm.ScalarMappable(cmap="turbo", norm=matplotlib.colors.Normalize(0, vmax_mm))
    fig.colorbar(sm, ax=axes[0].tolist(), fraction=0.025, pad=0.02, label="point-to-surface distance [mm]",
                 extend="max" if above.any() else "neither")
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


def save_depth_error_by_range(bins: list[dict], path: str | Path, title: str = "depth error by relative depth") -> Path:
    """PNG bar chart of :func:`~endorecon.evaluation.depth_metrics.depth_error_by_range`'s bins: the signed mean
    log error per band (bars; + too far, − too near) and each band's share of the pixels (line, right axis)."""
    from endorecon.evaluation.depth_metrics import range_label

    names = [range_label(b) for b in bins]
    err = np.array([np.nan if b["log_error"] is None else b["log_error"] for b in bins])
    x = np.arange(len(bins))
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.bar(x, np.nan_to_num(err), color=["C3" if e < 0 else "C0" for e in np.nan_to_num(err)])
    for xi, e, b in zip(x, err, bins):
        label = "n/a" if np.isnan(e) else f"{e:+.2f}\nAbsRel {b['abs_rel']:.2f}"
        ax.annotate(label, (xi, 0 if np.isnan(e) else e), ha="center", va="bottom" if not e < 0 else "top", fontsize=7)
    ax.axhline(0, color="k", lw=0.8)
    ax.margins(y=0.2)  # room for the labels beyond the longest bars
    ax.set_xticks(x, names)
    ax.set_xlabel("GT depth / frame's median GT depth")
    ax.set_ylabel("mean log(pred / GT)  (+ too far, − too near)")
    share = ax.twinx()
    share.plot(x, [100 * b["share"] for b in bins], "k.:", lw=1)
    share.set_ylabel("share of pixels [%]")
    share.set_ylim(bottom=0)
    ax.set_title(title)
    return _save(fig, path)


def _save(fig, path: str | Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return Path(path)


# ------------------------------------------------------------------ mesh preview
def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """cam_from_world (4, 4) of a camera at ``eye`` looking at ``target`` (x right, y down, z forward), with
    world direction ``up`` appearing upwards in the image."""
    z = np.asarray(target, np.float64) - np.asarray(eye, np.float64)
    z /= np.linalg.norm(z)
    u = np.asarray(up, np.float64)
    u = u - (u @ z) * z
    if np.linalg.norm(u) < 1e-9:  # up parallel to the view: any perpendicular will do
        u = np.eye(3)[int(np.argmin(np.abs(z)))]
        u = u - (u @ z) * z
    y = -u / np.linalg.norm(u)
    x = np.cross(y, z)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z])
    T[:3, 3] = -T[:3, :3] @ np.asarray(eye, np.float64)
    return T


def _pinhole(fov_deg: float, height: int, width: int) -> np.ndarray:
    f = 0.5 * width / np.tan(np.deg2rad(fov_deg) / 2)
    return np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]], np.float64)


def shade_view(renderer, vertex_rgb: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray, height: int,
               width: int, ambient: float = 0.25) -> np.ndarray:
    """One view (height, width, 3) float in [0, 1]: vertex colours (V, 3) in [0, 1] interpolated with the hit's
    barycentrics, Lambert-shaded with a headlight (two-sided: |n·ray|); white where nothing is hit.

    renderer: a :class:`endorecon.rendering.raycast.MeshRenderer`; K (3, 3) pixel-centre; cam_from_world (4, 4).
    """
    r = renderer.render(K, cam_from_world, height, width)
    hit = r["hit"]
    img = np.ones((height, width, 3))
    if not hit.any():
        return img
    tri = renderer.triangles[r["triangle_ids"][hit]]
    uv = r["uvs"][hit].astype(np.float64)
    c = vertex_rgb[tri]  # (K, 3 corners, 3)
    rgb = (1 - uv.sum(1, keepdims=True)) * c[:, 0] + uv[:, :1] * c[:, 1] + uv[:, 1:] * c[:, 2]
    eye = -cam_from_world[:3, :3].T @ cam_from_world[:3, 3]
    ray = r["points_world"][hit] - eye
    ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
    lambert = np.abs((r["normals_world"][hit] * ray).sum(1))
    img[hit] = np.clip(rgb * (ambient + (1 - ambient) * lambert)[:, None], 0, 1)
    return img


def _preview_cameras(vertices: np.ndarray, cam_from_world: np.ndarray | None, fov_deg: float, height: int,
                     width: int):
    """(title, cam_from_world) of the preview views: an endoscope-like view behind the middle registered camera
    (if poses are given) and an overview from outside along the mesh's thinnest axis."""
    centre = 0.5 * (vertices.min(0) + vertices.max(0))
    radius = float(np.linalg.norm(vertices - centre, axis=1).max())
    _, _, Vt = np.linalg.svd(vertices - vertices.mean(0), full_matrices=False)
    views = []
    if cam_from_world is not None:
        ok = np.flatnonzero(np.isfinite(cam_from_world).all(axis=(1, 2)))
        if len(ok):
            T = cam_from_world[ok[len(ok) // 2]]
            R, t = T[:3, :3], T[:3, 3]
            eye, fwd, down = -R.T @ t, R[2], R[1]
            depth = np.median(np.linalg.norm(vertices - eye, axis=1))
            eye_back = eye - 0.75 * depth * fwd  # step back so more than the camera's own view fits
            views.append(("endoscope view (stepped back)", look_at(eye_back, eye_back + fwd, -down)))
            # the overview looks from the side the cameras are on (inside the cavity)
            side = Vt[2] if (eye - centre) @ Vt[2] >= 0 else -Vt[2]
            dist = _fit_distance(radius, fov_deg, height, width)
            views.append(("overview", look_at(centre + dist * side, centre, Vt[0])))
            return views
    dist = _fit_distance(radius, fov_deg, height, width)
    views.append(("overview", look_at(centre - dist * Vt[2], centre, Vt[0])))
    views.append(("overview (other side)", look_at(centre + dist * Vt[2], centre, Vt[0])))
    return views


def render_mesh_preview(mesh_path: str | Path, png_path: str | Path, K: np.ndarray | None = None,
                        cam_from_world: np.ndarray | None = None, height: int | None = None,
                        width: int | None = None, size: tuple[int, int] = (300, 380), fov_deg: float = 60.0,
                        show_std: bool = True, title: str | None = None, units: str = "mesh units") -> Path:
    """PNG of a (fused) mesh: shaded vertex colours from two viewpoints, plus its per-vertex std if it has one.

    Args:
        mesh_path: PLY with vertex colours (grey if none); a ``std`` vertex property (endorecon's fusion) adds a
            std panel.
        png_path: output PNG (written atomically).
        K, cam_from_world (N, 4, 4), height, width: the cameras that saw the mesh (optional); with them the first
            view is an endoscope-like view from behind the middle camera, else two outside views.
        size: (height, width) of each rendered view.
        units: the mesh's length unit, for the std colour bar's label.
    """
    from endorecon.fusion.ply import read_mesh_ply
    from endorecon.rendering.raycast import MeshRenderer

    mesh_path = Path(mesh_path)
    try:
        tm = read_mesh_ply(mesh_path)
        v = tm.vertex
        verts = v.positions.numpy().astype(np.float64)
        tris = tm.triangle.indices.numpy().astype(np.int64)
        rgb = v.colors.numpy().astype(np.float64) if "colors" in v else None
        std = v["std"].numpy().reshape(-1).astype(np.float64) if "std" in v else None
    except Exception:  # not one of endorecon's binary PLYs: any mesh Open3D reads
        m = o3d.io.read_triangle_mesh(str(mesh_path))
        verts, tris = np.asarray(m.vertices, np.float64), np.asarray(m.triangles, np.int64)
        rgb = np.asarray(m.vertex_colors, np.float64) if m.has_vertex_colors() else None
        std = None
    if len(tris) == 0:
        from endorecon.utils.errors import InputError

        raise InputError("mesh has no triangles: nothing to preview", mesh_path, "check the fusion stage's log")
    if rgb is None or len(rgb) != len(verts):
        rgb = np.full((len(verts), 3), 0.8)
    renderer = MeshRenderer((verts, tris))
    H, W = size
    Kp = _pinhole(fov_deg, H, W)
    views = _preview_cameras(verts, cam_from_world, fov_deg, H, W)
    panels = [(name, shade_view(renderer, rgb, Kp, T, H, W)) for name, T in views]
    std_img = None
    if show_std and std is not None and np.isfinite(std).any():
        lo, hi = np.nanpercentile(std, [2, 98])
        hi = max(hi, lo + 1e-12)
        std_rgb = plt.get_cmap("magma")(np.clip((std - lo) / (hi - lo), 0, 1))[:, :3]
        std_img = shade_view(renderer, std_rgb, Kp, views[-1][1], H, W, ambient=0.5)
    n = len(panels) + (std_img is not None)
    fig, axes = plt.subplots(1, n, figsize=(3.4 * n + 0.6, 3.4 * H / W + 0.7), squeeze=False)
    for ax, (name, img) in zip(axes[0], panels):
        ax.imshow(img)
        ax.set_title(name, fontsize=9)
        ax.set_axis_off()
    if std_img is not None:
        ax = axes[0, -1]
        ax.imshow(std_img)
        ax.set_title("per-vertex std (overview)", fontsize=9)
        ax.set_axis_off()
        sm = plt.cm.ScalarMappable(cmap="magma", norm=matplotlib.colors.Normalize(lo, hi))
        fig.colorbar(sm, ax=ax, fraction=0.046, pad=0.02, label=f"fused std ({units})")
    fig.suptitle(title or f"{mesh_path.name}: {len(verts)} vertices, {len(tris)} triangles", fontsize=10)
    return _save(fig, png_path)
