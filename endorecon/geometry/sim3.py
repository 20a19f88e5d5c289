"""Similarity alignment (Umeyama) of two point sets, for SfM-vs-GT and registration init."""

from __future__ import annotations

import numpy as np
import torch


def umeyama(src, dst, with_scale: bool = True):
    """Least-squares similarity dst ≈ s R src + t (Umeyama 1991).

    Args:
        src: (N, 3) torch tensor or numpy array, N >= 3 (non-collinear).
        dst: (N, 3), same kind as ``src``.
        with_scale: estimate s (else s = 1).
    Returns:
        (scale, R (3, 3), t (3,)) as the input's kind (numpy float64 / torch of src's dtype).
    """
    is_np = not isinstance(src, torch.Tensor)
    s_t = torch.as_tensor(np.asarray(src) if is_np else src, dtype=torch.float64)
    d_t = torch.as_tensor(np.asarray(dst) if is_np else dst, dtype=torch.float64)
    if s_t.ndim != 2 or s_t.shape[1] != 3 or s_t.shape != d_t.shape:
        raise ValueError(f"src and dst must both be (N, 3), got {tuple(s_t.shape)} and {tuple(d_t.shape)}")
    if s_t.shape[0] < 3:
        raise ValueError(f"need at least 3 point pairs, got {s_t.shape[0]}")
    if not (torch.isfinite(s_t).all() and torch.isfinite(d_t).all()):
        raise ValueError("src/dst contain non-finite values")
    mu_s, mu_d = s_t.mean(0), d_t.mean(0)
    xs, xd = s_t - mu_s, d_t - mu_d
    var_s = (xs * xs).sum() / len(xs)
    if with_scale and not var_s > 1e-12 * max(1.0, float((s_t * s_t).sum() / len(s_t))):
        raise ValueError("src points all coincide: no similarity (scale) can be estimated from them")
    var_d = (xd * xd).sum() / len(xd)
    if with_scale and not var_d > 1e-12 * max(1.0, float((d_t * d_t).sum() / len(d_t))):
        # the least-squares scale would be 0: every src point mapped onto one dst point
        raise ValueError("dst points all coincide: no similarity (scale) maps src onto them")
    cov = xd.T @ xs / len(xs)
    U, S, Vh = torch.linalg.svd(cov)
    D = torch.eye(3, dtype=torch.float64)
    if torch.det(U) * torch.det(Vh) < 0:
        D[2, 2] = -1
    R = U @ D @ Vh
    scale = (S * D.diagonal()).sum() / var_s if with_scale else torch.tensor(1.0, dtype=torch.float64)
    t = mu_d - scale * (R @ mu_s)
    if is_np:
        return float(scale), R.numpy(), t.numpy()
    dt = src.dtype
    return scale.to(dt), R.to(dt), t.to(dt)


def apply_sim3(scale, R, t, points):
    """s R p + t for points (N, 3) (numpy or torch)."""
    return scale * points @ R.T + t
