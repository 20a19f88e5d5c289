"""Endoscope camera model and hand-held-like trajectories inside a cavity.

:func:`endoscope_camera` gives pinhole intrinsics (pixel-centre convention) and
the circular valid-pixel mask.  :func:`plan_trajectory` moves a camera along a
centreline: forward with a slow back-and-forth, a lateral drift kept within a
fraction of the local clearance, small yaw/pitch around the (smoothed) passage
direction and a slow roll, all smooth (sums of low-frequency sinusoids) and at
video-rate speeds: ~0.35 mm forward and a few tenths of a degree of rotation per
frame, as a hand-held scope moves (what SfM on real video sees).
:func:`estimate_centreline` finds a path of large clearance through any closed
mesh (the given-mesh phantom): Dijkstra over interior voxels, weighted by
inverse clearance, between the two far ends of the cavity's principal axis.
"""

from __future__ import annotations

import numpy as np

from endorecon.phantom.anatomy import rotation_minimising_frames
from endorecon.utils.errors import InputError

__all__ = ["endoscope_camera", "plan_trajectory", "estimate_centreline", "centreline_from_waypoints"]


def endoscope_camera(height: int, width: int, fov_deg: float = 100.0, mask_radius: float = 0.56) -> tuple[np.ndarray, np.ndarray]:
    """Intrinsics and mask of an endoscope.

    Args:
        height, width: image size.
        fov_deg: field of view across the diameter of the circular mask.
        mask_radius: circle radius as a fraction of the height (> 0.5 clips it at top and bottom, as many scopes).
    Returns:
        K (3, 3) float64, pixel-centre convention; mask (H, W) bool, True inside the circle.
    """
    if height < 8 or width < 8:
        raise InputError(f"image size {width}x{height} is too small", fix="use at least 8x8 pixels")
    if not 20.0 <= fov_deg <= 170.0:
        raise InputError(f"fov_deg={fov_deg} outside [20, 170]", fix="pass a field of view in degrees, e.g. 100")
    r = mask_radius * height
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    f = r / np.tan(np.deg2rad(fov_deg) / 2)
    K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    v, u = np.mgrid[0:height, 0:width]
    mask = (u - cx) ** 2 + (v - cy) ** 2 <= r**2
    return K, mask


def _series(rng: np.random.Generator, t: np.ndarray, periods: tuple[float, float], n: int = 3) -> np.ndarray:
    out = np.zeros_like(t, dtype=np.float64)
    for _ in range(n):
        out += rng.normal() * np.sin(2 * np.pi * t / rng.uniform(*periods) + rng.uniform(0, 2 * np.pi))
    return out / np.sqrt(n)


def _interp_rows(x: np.ndarray, xp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(x, xp, fp[:, k]) for k in range(fp.shape[1])], 1)


def plan_trajectory(
    centreline: np.ndarray,
    clearance: np.ndarray,
    n_frames: int,
    rng: np.random.Generator,
    step_mm: float = 0.35,
    margin_mm: float = 20.0,
    times: np.ndarray | None = None,
    view_smoothing_mm: float = 12.0,
) -> np.ndarray:
    """Smooth hand-held-like camera poses along a centreline.

    Args:
        centreline: (M, 3) ordered axis samples (mm).
        clearance: (M,) wall distance at each sample (limits the lateral drift).
        n_frames: number of frames.
        rng: random generator.
        step_mm: mean forward motion per frame.
        margin_mm: distance kept from both ends of the centreline.
        times: optional (T,) times in frame units at which to evaluate the poses (default
            ``arange(n_frames)``; fractional times around a frame give motion-blur sub-poses; the
            trajectory itself depends only on ``rng`` and ``n_frames``, not on ``times``).
        view_smoothing_mm: the scope looks along the passage direction averaged over this arc length
            (Gaussian sigma), so bends of the passage turn the view gradually.
    Returns:
        cam_from_world (T, 4, 4) float64.
    """
    c = np.asarray(centreline, dtype=np.float64)
    seg = np.linalg.norm(np.diff(c, axis=0), axis=1)
    s_c = np.concatenate([[0.0], np.cumsum(seg)])
    length = s_c[-1]
    tan, nor, bin_ = _smoothed_frames(c, s_c, view_smoothing_mm)
    usable = length - 2 * margin_mm
    if usable <= 1.0:
        raise InputError(f"centreline is only {length:.1f} mm long", fix="use a longer cavity or smaller margin_mm")
    t = np.arange(n_frames, dtype=np.float64) if times is None else np.asarray(times, dtype=np.float64)
    # forward motion with back-and-forth: the speed step_mm * (1 + 1.15 sin) briefly goes backwards and
    # peaks at ~2 step_mm (faster forward motion near a wall changes the view too much for SfM)
    period = max(24.0, n_frames / 2.5)
    amp = 1.15 * step_mm * period / (2 * np.pi)
    travel = min(step_mm * max(n_frames - 1, 1), usable - 2 * amp)
    travel = max(travel, 0.0)
    start = margin_mm + amp + rng.uniform(0, max(usable - 2 * amp - travel, 0.0))
    s = start + travel * t / max(n_frames - 1, 1) + amp * np.sin(2 * np.pi * t / period + rng.uniform(0, 2 * np.pi))
    s = np.clip(s, margin_mm, length - margin_mm)
    p = _interp_rows(s, s_c, c)
    T_ = _unit(_interp_rows(s, s_c, tan))
    N_ = _interp_rows(s, s_c, nor)
    N_ = _unit(N_ - T_ * np.sum(N_ * T_, 1, keepdims=True))
    B_ = np.cross(T_, N_)
    cl = np.interp(s, s_c, clearance)
    # lateral drift within 25 % of the clearance, slow (a hand drifts over seconds, not frames)
    lat = 0.25 * cl[:, None] * np.stack([_series(rng, t, (60, 160)), _series(rng, t, (60, 160))], 1) / 1.5
    lat = np.clip(lat, -0.25 * cl[:, None], 0.25 * cl[:, None])
    pos = p + lat[:, :1] * N_ + lat[:, 1:] * B_
    # view direction: passage direction tilted by small yaw/pitch, slow roll.  Amplitude / period
    # keeps each at a few tenths of a degree per frame (a scope at video rate turns slowly; together
    # with the bends of the passage ~0.3-0.8 deg/frame)
    yaw = np.deg2rad(7) * _series(rng, t, (100, 240))
    pitch = np.deg2rad(5) * _series(rng, t, (100, 240))
    roll = np.deg2rad(10) * _series(rng, t, (200, 500)) + rng.uniform(0, 2 * np.pi)
    fwd = T_ + np.tan(yaw)[:, None] * N_ + np.tan(pitch)[:, None] * B_
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
    up0 = B_ - fwd * np.sum(B_ * fwd, 1, keepdims=True)
    up0 /= np.linalg.norm(up0, axis=1, keepdims=True)
    right0 = np.cross(up0, fwd)
    x_axis = np.cos(roll)[:, None] * right0 + np.sin(roll)[:, None] * up0
    y_axis = np.cross(fwd, x_axis)  # camera y points down in the image, z forward: right-handed x, y, z
    R = np.stack([x_axis, y_axis, fwd], axis=1)  # rows = camera axes in world: x_cam = R (x_w - c)
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = -np.einsum("nij,nj->ni", R, pos)
    return T


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _smoothed_frames(c: np.ndarray, s_c: np.ndarray, sigma_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotation-minimising frames of the centreline with its tangent low-passed over ``sigma_mm`` of arc length."""
    tan, nor, bin_ = rotation_minimising_frames(c)
    if sigma_mm <= 0 or len(c) < 3:
        return tan, nor, bin_
    from scipy.ndimage import gaussian_filter1d

    ds = max(float(np.median(np.diff(s_c))), 1e-9)
    tan_s = _unit(gaussian_filter1d(tan, sigma=sigma_mm / ds, axis=0, mode="nearest"))
    nor_s = nor - tan_s * np.sum(nor * tan_s, 1, keepdims=True)  # keep the twist-free normal, re-orthogonalised
    nor_s = _unit(nor_s)
    return tan_s, nor_s, np.cross(tan_s, nor_s)


def centreline_from_waypoints(waypoints: np.ndarray, spacing_mm: float = 0.5) -> np.ndarray:
    """Resample a polyline of user waypoints (K, 3) into a smooth centreline (M, 3)."""
    w = np.asarray(waypoints, dtype=np.float64)
    if w.ndim != 2 or w.shape[1] != 3 or len(w) < 2:
        raise InputError(f"waypoints must be (K >= 2, 3) in mm, got shape {w.shape}", fix="give at least two x,y,z points")
    from scipy.interpolate import CubicSpline

    seg = np.linalg.norm(np.diff(w, axis=0), axis=1)
    if np.any(seg <= 0):
        raise InputError("waypoints repeat a point", fix="remove duplicate waypoints")
    u = np.concatenate([[0.0], np.cumsum(seg)])
    spline = CubicSpline(u, w, bc_type="natural") if len(w) > 2 else None
    uu = np.linspace(0, u[-1], max(int(u[-1] / spacing_mm), 2) + 1)
    return spline(uu) if spline is not None else w[0] + (w[1] - w[0]) * (uu / u[-1])[:, None]


def estimate_centreline(renderer, voxel_mm: float = 1.0, min_clearance_mm: float = 1.5, spacing_mm: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """A path of large clearance through a closed mesh, end to end along its longest axis.

    Args:
        renderer: a :class:`endorecon.rendering.MeshRenderer` of a watertight mesh (the cavity's wall).
        voxel_mm: grid spacing of the search.
        min_clearance_mm: interior voxels closer to the wall than this are not used.
        spacing_mm: sample spacing of the returned centreline.
    Returns:
        centreline (M, 3) mm, clearance (M,) mm.
    """
    from scipy.ndimage import gaussian_filter1d
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    lo = renderer.vertices.min(0)
    hi = renderer.vertices.max(0)
    axes = [np.arange(lo[k] + voxel_mm / 2, hi[k], voxel_mm) for k in range(3)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    shape = g.shape[:3]
    pts = g.reshape(-1, 3)
    inside = renderer.occupancy(pts)
    clear = np.zeros(len(pts))
    clear[inside] = renderer.distance(pts[inside])
    ok = inside & (clear >= min_clearance_mm)
    if ok.sum() < 10:
        raise InputError(
            f"no interior space with enough clearance for an endoscope in this mesh (under 10 voxels of "
            f"{voxel_mm} mm at least {min_clearance_mm} mm from the wall)",
            fix="the mesh must be a closed cavity wall in mm (e.g. ASR.ply), a few mm wide or more",
        )
    idx = -np.ones(len(pts), np.int64)
    idx[ok] = np.arange(ok.sum())
    idx3 = idx.reshape(shape)
    rows, cols, w = [], [], []
    node_clear = clear[ok]
    for d in [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 0, 1), (0, 1, 1), (1, -1, 0), (1, 0, -1), (0, 1, -1)]:
        sl_a = tuple(slice(max(-k, 0), shape[i] - max(k, 0)) for i, k in enumerate(d))
        sl_b = tuple(slice(max(k, 0), shape[i] - max(-k, 0)) for i, k in enumerate(d))
        a, b = idx3[sl_a].ravel(), idx3[sl_b].ravel()
        keep = (a >= 0) & (b >= 0)
        a, b = a[keep], b[keep]
        length = voxel_mm * np.linalg.norm(d)
        # cost: length / clearance^2 prefers the middle of the passage strongly
        cost = length / (0.5 * (node_clear[a] + node_clear[b])) ** 2
        rows += [a, b]
        cols += [b, a]
        w += [cost, cost]
    n = int(ok.sum())
    graph = coo_matrix((np.concatenate(w), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
    p_ok = pts[ok]
    # narrow cavities fall apart into pieces at this clearance: plan in the largest one
    from scipy.sparse.csgraph import connected_components

    _, label = connected_components(graph, directed=False)
    comp = np.flatnonzero(label == np.bincount(label).argmax())
    # ends: well-cleared nodes at the two extremes of the component's principal axis
    centred = p_ok[comp] - p_ok[comp].mean(0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    proj = centred @ axis
    good = node_clear[comp] >= np.percentile(node_clear[comp], 50)
    a, b = comp[good][np.argmin(proj[good])], comp[good][np.argmax(proj[good])]
    dist, pred = dijkstra(graph, indices=a, return_predecessors=True)
    path = [b]
    while path[-1] != a:
        path.append(pred[path[-1]])
    line = p_ok[np.array(path[::-1])]
    line = gaussian_filter1d(line, sigma=3.0, axis=0, mode="nearest")
    centre = centreline_from_waypoints(line[:: max(1, len(line) // 40)] if len(line) > 80 else line, spacing_mm)
    return centre, renderer.distance(centre)
