"""Procedural nasal-cavity-like anatomies: one watertight tube mesh (mm) per patient.

A patient is a curved passage around a smooth centreline (gentle curvature, so
the tube never folds onto itself) whose cross-section is an ellipse 8-30 mm
across, narrowed by turbinate-like folds that run along part of its length,
with small longitudinal ridges and random bumps.  The surface is a (s, theta)
grid closed by two small end caps, so the mesh is watertight: the patient's
"CT".  Everything is drawn from ``numpy.random.default_rng(seed)``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["Anatomy", "make_anatomy", "rotation_minimising_frames"]


@dataclasses.dataclass
class Anatomy:
    """One procedural patient.

    Attributes:
        vertices: (V, 3) float64 in mm.
        triangles: (F, 3) int64, normals pointing out of the cavity.
        centreline: (M, 3) float64 samples of the passage axis in mm.
        arclength: (M,) float64 arc length of each centreline sample.
        tangents, normals, binormals: (M, 3) rotation-minimising frame along the centreline.
        clearance: (M,) float64 smallest wall radius of each cross-section (mm).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    centreline: np.ndarray
    arclength: np.ndarray
    tangents: np.ndarray
    normals: np.ndarray
    binormals: np.ndarray
    clearance: np.ndarray


def _smooth_series(rng: np.random.Generator, s: np.ndarray, wavelengths: tuple[float, float], n: int) -> np.ndarray:
    """Sum of ``n`` random sinusoids of the given wavelength range, unit-ish amplitude."""
    out = np.zeros_like(s)
    for _ in range(n):
        lam = rng.uniform(*wavelengths)
        out += rng.normal() * np.sin(2 * np.pi * s / lam + rng.uniform(0, 2 * np.pi))
    return out / np.sqrt(n)


def rotation_minimising_frames(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tangent, normal, binormal (M, 3) along a polyline (M, 3) by parallel transport (no twist)."""
    t = np.gradient(points, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    n = np.zeros_like(t)
    a = np.array([0.0, 1.0, 0.0]) if abs(t[0, 1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    n[0] = a - t[0] * (a @ t[0])
    n[0] /= np.linalg.norm(n[0])
    for i in range(1, len(t)):
        v = n[i - 1] - t[i] * (n[i - 1] @ t[i])
        n[i] = v / np.linalg.norm(v)
    b = np.cross(t, n)
    return t, n, b


def make_anatomy(seed: int, length_mm: float = 100.0, ds_mm: float = 0.4, n_theta: int = 192) -> Anatomy:
    """Draw one patient's passage.

    Args:
        seed: anatomy seed (same seed, same mesh bytes).
        length_mm: length of the passage along its centreline.
        ds_mm: spacing of the cross-sections.
        n_theta: vertices per cross-section.
    """
    rng = np.random.default_rng(seed)
    m = int(round(length_mm / ds_mm)) + 1
    s = np.linspace(0.0, length_mm, m)

    # centreline: heading angles vary slowly (curvature radius >~ 40 mm > the widest radius)
    yaw = 0.35 * _smooth_series(rng, s, (70, 160), 3)
    pitch = 0.25 * _smooth_series(rng, s, (70, 160), 3)
    d = np.stack([np.sin(yaw) * np.cos(pitch), np.sin(pitch), np.cos(yaw) * np.cos(pitch)], 1)
    centre = np.concatenate([np.zeros((1, 3)), np.cumsum((d[1:] + d[:-1]) * 0.5 * ds_mm, axis=0)])
    tan, nor, bin_ = rotation_minimising_frames(centre)

    # cross-section: ellipse with radius 4..15 mm (8..30 mm across) and varying aspect
    mean_r = rng.uniform(7.0, 10.0) + 2.5 * _smooth_series(rng, s, (30, 80), 3)
    mean_r = np.clip(mean_r, 4.5, 14.0)
    aspect = 1.0 + 0.35 * (1 + _smooth_series(rng, s, (40, 120), 2))  # ~1 .. 1.8: taller than wide
    aspect = np.clip(aspect, 1.0, 1.9)
    a = mean_r / np.sqrt(aspect)  # along the normal
    b = mean_r * np.sqrt(aspect)  # along the binormal
    theta = 2 * np.pi * np.arange(n_theta) / n_theta
    ct, st = np.cos(theta)[None], np.sin(theta)[None]
    rho = (a * b)[:, None] / np.sqrt((b[:, None] * ct) ** 2 + (a[:, None] * st) ** 2)

    # turbinate-like folds: lobes from the lateral wall over part of the length
    n_folds = int(rng.integers(2, 4))
    for k in range(n_folds):
        th0 = rng.normal(0.0, 0.35) + (k - (n_folds - 1) / 2) * 0.9  # stacked on one side, like turbinates
        width = rng.uniform(0.25, 0.45)
        s0 = rng.uniform(0.05, 0.45) * length_mm
        s1 = min(s0 + rng.uniform(0.35, 0.6) * length_mm, 0.97 * length_mm)
        amp = rng.uniform(0.25, 0.45)
        ramp = _smoothstep((s - s0) / 8.0) * _smoothstep((s1 - s) / 8.0)
        wobble = 0.15 * _smooth_series(rng, s, (10, 30), 2)  # the fold meanders
        dth = np.angle(np.exp(1j * (theta[None] - th0 - wobble[:, None])))
        rho *= 1 - (amp * ramp)[:, None] * np.exp(-0.5 * (dth / width) ** 2)
    # small longitudinal ridges, flattening out towards the closed ends (ridges that converge on the
    # end dome would shade as a star)
    ridge_env = _smoothstep((np.minimum(s, length_mm - s) - 8.0) / 12.0)
    for _ in range(3):
        k = int(rng.integers(5, 11))
        phase = rng.uniform(0, 2 * np.pi) + 0.5 * _smooth_series(rng, s, (20, 60), 2)
        rho *= 1 + 0.015 * ridge_env[:, None] * np.cos(k * theta[None] + phase[:, None])
    # bumps: Gaussian blobs in (s, arc length) of 1-4 mm
    arc = theta[None] * rho.mean(axis=1, keepdims=True)
    circ = 2 * np.pi * rho.mean(axis=1, keepdims=True)
    for _ in range(int(rng.integers(25, 40))):
        sc, tc = rng.uniform(0, length_mm), rng.uniform(0, 2 * np.pi)
        sig = rng.uniform(1.0, 4.0)
        h = rng.uniform(-0.8, 0.8) * sig * 0.5
        da = arc - tc * circ / (2 * np.pi)
        da = (da + circ / 2) % circ - circ / 2
        rho += h * np.exp(-0.5 * (((s[:, None] - sc) ** 2 + da**2) / sig**2))
    # dome-shaped closed ends over the last 10 mm (a tiny cap instead of a wide flat disk)
    d_end = np.minimum(s, length_mm - s) / 10.0
    taper = np.sqrt(np.clip(1 - (1 - np.minimum(d_end, 1.0)) ** 2, 0.0025, 1.0))
    rho *= taper[:, None]
    rho = np.maximum(rho, 0.3)

    offs = rho[..., None] * (ct[..., None] * nor[:, None] + st[..., None] * bin_[:, None])
    ring_pts = centre[:, None] + offs  # (M, T, 3)
    vertices = np.concatenate([ring_pts.reshape(-1, 3), centre[[0, -1]]])
    i = np.arange(n_theta)
    j = (i + 1) % n_theta
    faces = []
    for r in range(m - 1):
        a0, a1 = r * n_theta, (r + 1) * n_theta
        faces.append(np.stack([a0 + i, a1 + i, a1 + j], 1))
        faces.append(np.stack([a0 + i, a1 + j, a0 + j], 1))
    first, last = m * n_theta, m * n_theta + 1
    faces.append(np.stack([np.full(n_theta, first), i, j], 1))
    faces.append(np.stack([np.full(n_theta, last), (m - 1) * n_theta + j, (m - 1) * n_theta + i], 1))
    triangles = np.concatenate(faces).astype(np.int64)
    # orient normals out of the cavity (outward from the centreline)
    v0, v1, v2 = (vertices[triangles[: n_theta * 2, k]] for k in range(3))
    fn = np.cross(v1 - v0, v2 - v0)
    if np.sum(fn * (v0 - centre[0])) < 0:
        triangles = triangles[:, [0, 2, 1]]
    return Anatomy(vertices, triangles, centre, s, tan, nor, bin_, rho.min(axis=1))


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)
