"""The four Gaussian negative log-likelihood losses of the depth network.

Per element, with predicted mean μ, variance σ² and observation x,

    nll = 0.5·log(σ² + eps) + (x − μ)² / (2·(σ² + eps))

i.e. −log N(x; μ, σ²) without its constant 0.5·log(2π) (dropped everywhere:
it shifts every value and no gradient).  eps = 1e-8 keeps it finite at σ = 0.
Identical x and μ give the minimum over x of 0.5·log(σ² + eps).

Reductions (every loss): ``"none"`` returns (B,): per sample, the mean of the
per-pixel NLL over its valid pixels (0 where a sample has none, NaN where it has
fewer than ``min_valid`` when that is given: a check must not read "no overlap" as a value);
``"mean"`` returns a scalar: the sum over every valid pixel of the batch divided
by their number (0 if none).  Invalid pixels never contribute, neither to the
value nor to the gradient, even if they hold NaN or inf: inputs are replaced by
safe constants there *before* any arithmetic.

Poses and intrinsics are plain tensor inputs and every loss is differentiable
w.r.t. them (dense pose graph optimisation uses them per frame with poses as
variables).
"""

from __future__ import annotations

import torch

from endorecon.geometry import flow_from_depth, project, unproject, warp_depth
from endorecon.geometry._checks import check_shape

_REDUCTIONS = ("mean", "none")


def _safe(x: torch.Tensor, valid: torch.Tensor, fill: float) -> torch.Tensor:
    """x where valid, ``fill`` elsewhere (no NaN/inf from invalid pixels reaches arithmetic or gradients)."""
    return torch.where(valid, x, torch.full_like(x, fill))


def _reduce(per_pixel: torch.Tensor, valid: torch.Tensor, reduction: str, min_valid: int = 0) -> torch.Tensor:
    """per_pixel, valid: (B, 1, H, W) -> scalar ("mean") or (B,) ("none"; NaN where a sample has fewer
    than ``min_valid`` valid pixels)."""
    if reduction not in _REDUCTIONS:
        raise ValueError(f"reduction must be one of {_REDUCTIONS}, got {reduction!r}")
    v = valid.to(per_pixel.dtype)
    total = (per_pixel * v).flatten(1).sum(1)
    count = v.flatten(1).sum(1)
    if reduction == "none":
        out = total / count.clamp(min=1)
        return torch.where(count < min_valid, torch.full_like(out, float("nan")), out) if min_valid > 0 else out
    return total.sum() / count.sum().clamp(min=1)


def gaussian_nll(
    x: torch.Tensor, mu: torch.Tensor, var: torch.Tensor, eps: float = 1e-8
) -> torch.Tensor:
    """Element-wise 0.5·log(var + eps) + (x − μ)²/(2(var + eps)); x, mu, var: one shape, the output's."""
    if not (x.shape == mu.shape == var.shape):  # broadcasting would give a plausible loss of the wrong pixels
        raise ValueError(f"x, mu and var must have one shape, got {tuple(x.shape)}, {tuple(mu.shape)}, "
                         f"{tuple(var.shape)}")
    v = var + eps
    return 0.5 * torch.log(v) + (x - mu) ** 2 / (2 * v)


def _check_map(x: torch.Tensor, name: str, ref: tuple, channels: int = 1) -> None:
    check_shape(x, name, (ref[0], channels, ref[2], ref[3]))


def _pixel_nll(
    depth: torch.Tensor,
    std: torch.Tensor,
    obs: torch.Tensor,
    obs_valid: torch.Tensor,
    eps: float,
    reduction: str,
    min_valid: int = 0,
) -> torch.Tensor:
    shape = check_shape(depth, "depth", (None, 1, None, None))
    _check_map(std, "std", shape)
    _check_map(obs, "observed depth", shape)
    _check_map(obs_valid, "observed validity", shape)
    valid = obs_valid.bool() & torch.isfinite(obs) & torch.isfinite(depth) & torch.isfinite(std)
    nll = gaussian_nll(_safe(obs, valid, 1.0), _safe(depth, valid, 1.0), _safe(std, valid, 1.0) ** 2, eps)
    return _reduce(nll, valid, reduction, min_valid)


def sparse_depth_loss(
    depth: torch.Tensor,
    std: torch.Tensor,
    sparse_depth: torch.Tensor,
    sparse_valid: torch.Tensor,
    eps: float = 1e-8,
    reduction: str = "mean",
) -> torch.Tensor:
    """Sparse Depth loss: NLL of the SfM depth under the predicted N(depth, std²) at valid sparse points.

    Args:
        depth, std: (B, 1, H, W) scaled prediction.
        sparse_depth: (B, 1, H, W) SfM z-depth.  sparse_valid: (B, 1, H, W) bool.
    Returns:
        scalar ("mean") or (B,) ("none").
    """
    return _pixel_nll(depth, std, sparse_depth, sparse_valid, eps, reduction)


def dense_simulation_loss(
    depth: torch.Tensor,
    std: torch.Tensor,
    sim_depth: torch.Tensor,
    sim_valid: torch.Tensor,
    eps: float = 1e-8,
    reduction: str = "mean",
    min_valid: int = 0,
) -> torch.Tensor:
    """Dense Simulation loss: NLL of the depth rendered from the previous iteration's mesh.

    Zero when no pixel of ``sim_valid`` is set (iteration 0).

    Args:
        depth, std: (B, 1, H, W) scaled prediction.
        sim_depth: (B, 1, H, W) simulated z-depth.  sim_valid: (B, 1, H, W) bool.
    Returns:
        scalar ("mean") or (B,) ("none").
    """
    return _pixel_nll(depth, std, sim_depth, sim_valid, eps, reduction, min_valid)


def _check_pair(depth_i, std_i, depth_j, std_j, mask_i) -> tuple:
    shape = check_shape(depth_i, "depth_i", (None, 1, None, None))
    for x, name in ((std_i, "std_i"), (depth_j, "depth_j"), (std_j, "std_j"), (mask_i, "mask_i")):
        _check_map(x, name, shape)
    return shape


def consistency_inputs(depth_i, std_i, depth_j, std_j, mask_i, mask_j):
    """What the depth consistency terms compare: non-finite values, and j's outside ``mask_j``, set to 0
    (= invalid to the warp, which also refuses a sample that blends them in).

    Args: (B, 1, H, W) each; ``mask_j`` may be None.
    Returns: m_i (B, 1, H, W) bool (i's usable pixels), d_i, d_j, s_j (B, 1, H, W)."""
    m_i = mask_i.bool() & torch.isfinite(depth_i) & torch.isfinite(std_i)
    ok_j = torch.isfinite(depth_j) & torch.isfinite(std_j)
    if mask_j is not None:
        ok_j = ok_j & mask_j.bool()
    return m_i, _safe(depth_i, m_i, 0.0), _safe(depth_j, ok_j, 0.0), _safe(std_j, ok_j, 0.0)


def carried_std(
    depth_i: torch.Tensor,
    std_i: torch.Tensor,
    depth_j: torch.Tensor,
    std_j: torch.Tensor,
    K: torch.Tensor,
    cam_j_from_cam_i: torch.Tensor,
    mask_i: torch.Tensor,
    mask_j: torch.Tensor | None = None,
) -> torch.Tensor:
    """Frame j's depth std carried into frame i's pixels at the pose ``cam_j_from_cam_i``, for
    :func:`depth_consistency_loss`'s ``std_j_in_i``.

    Where that warp misses j, std_i stands in for j's std (so that the result is defined at every
    pixel the loss may use at any other pose).  Differentiable w.r.t. the depths, stds and pose.

    Args:
        depth_i, std_i, depth_j, std_j: (B, 1, H, W).  K: (B, 3, 3).  cam_j_from_cam_i: (B, 4, 4).
        mask_i: (B, 1, H, W) bool.
    Returns:
        (B, 1, H, W) std, 0 outside mask_i.
    """
    shape = _check_pair(depth_i, std_i, depth_j, std_j, mask_i)
    check_shape(cam_j_from_cam_i, "cam_j_from_cam_i", (shape[0], 4, 4))
    if mask_j is not None:
        _check_map(mask_j, "mask_j", depth_i.shape)
    m_i, d_i, d_j, s_j = consistency_inputs(depth_i, std_i, depth_j, std_j, mask_i, mask_j)
    _, valid, std_w = warp_depth(d_j, d_i, K, cam_j_from_cam_i.to(d_i.dtype), std_j=s_j)
    return torch.where(valid, std_w, _safe(std_i, m_i, 0.0))


def depth_consistency_loss(
    depth_i: torch.Tensor,
    std_i: torch.Tensor,
    depth_j: torch.Tensor,
    std_j: torch.Tensor,
    K: torch.Tensor,
    cam_j_from_cam_i: torch.Tensor,
    mask_i: torch.Tensor,
    eps: float = 1e-8,
    reduction: str = "mean",
    std_pose: torch.Tensor | None = None,
    std_j_in_i: torch.Tensor | None = None,
    mask_j: torch.Tensor | None = None,
    min_valid: int = 0,
) -> torch.Tensor:
    """Depth Consistency loss: frame j's depth warped into i vs frame i's depth.

    ``geometry.warp_depth`` expresses j's surface in i at i's pixels and carries
    std_j along linearly; the NLL uses μ = depth_i, x = warped depth_j and
    σ² = std_i² + std_j,warped², over the warp's valid overlap ∧ mask_i, where the
    overlap needs j's sample drawn from pixels inside ``mask_j`` (j's depth outside its
    endoscope mask is unconstrained output).  Non-finite depth values are set to 0
    (= invalid to the warp) first.

    Args:
        depth_i, std_i, depth_j, std_j: (B, 1, H, W) scaled predictions.
        K: (B, 3, 3) pixel-centre intrinsics.  cam_j_from_cam_i: (B, 4, 4).
        mask_i: (B, 1, H, W) bool.
        std_pose: optional (B, 4, 4) cam_j_from_cam_i at which std_j is carried into i (default:
            ``cam_j_from_cam_i``); no gradient flows into it.  Pose graph optimisation passes the initial poses: then
            σ² does not depend on the poses being optimised, so its log term cannot pull them (data that
            agree exactly at a pose make that pose a stationary point).
        std_j_in_i: optional (B, 1, H, W) std_j already carried into i (:func:`carried_std` at std_pose), so that
            a caller evaluating many poses computes it once; excludes ``std_pose``.
        mask_j: optional (B, 1, H, W) bool, frame j's valid pixels (None: every pixel with finite depth).
        min_valid: with ``reduction="none"``, NaN for a sample with fewer valid pixels (0: 0 for none).
    Returns:
        scalar ("mean") or (B,) ("none").
    """
    shape = _check_pair(depth_i, std_i, depth_j, std_j, mask_i)
    if std_pose is not None and std_j_in_i is not None:
        raise ValueError("pass std_pose or std_j_in_i (carried_std at std_pose), not both")
    if std_pose is not None:
        check_shape(std_pose, "std_pose", (shape[0], 4, 4))
        std_j_in_i = carried_std(depth_i, std_i, depth_j, std_j, K, std_pose.detach(), mask_i, mask_j)
    if std_j_in_i is not None:
        _check_map(std_j_in_i, "std_j_in_i", shape)
    if mask_j is not None:
        _check_map(mask_j, "mask_j", shape)
    m_i, d_i, d_j, s_j = consistency_inputs(depth_i, std_i, depth_j, std_j, mask_i, mask_j)
    warped, valid, std_w = warp_depth(d_j, d_i, K, cam_j_from_cam_i, std_j=s_j if std_j_in_i is None else None)
    valid = valid & m_i
    if std_j_in_i is not None:
        std_w = std_j_in_i.to(d_i.dtype)
    var = _safe(std_i, valid, 1.0) ** 2 + _safe(std_w, valid, 0.0) ** 2
    nll = gaussian_nll(_safe(warped, valid, 1.0), _safe(d_i, valid, 1.0), var, eps)
    return _reduce(nll, valid, reduction, min_valid)


def flow_depth_derivative(
    depth_i: torch.Tensor, K: torch.Tensor, cam_j_from_cam_i: torch.Tensor, z_j: torch.Tensor
) -> torch.Tensor:
    """∂flow/∂depth_i per pixel, closed form.

    With the ray r = K⁻¹(u, v, 1)ᵀ, a = R r and X_j = d·a + t, the normalised
    coordinate x = X_j,x / X_j,z has ∂x/∂d = (a_x t_z − t_x a_z) / z_j² (same for y);
    then ∂u/∂d = f_x ∂x/∂d + s ∂y/∂d and ∂v/∂d = f_y ∂y/∂d.

    Args:
        depth_i: (B, 1, H, W) (only its shape is used).  K: (B, 3, 3).  cam_j_from_cam_i: (B, 4, 4).
        z_j: (B, 1, H, W) depth of i's points in j (from ``flow_from_depth``), must be nonzero.
    Returns:
        (B, 2, H, W) pixels per depth unit.
    """
    B, _, H, W = check_shape(depth_i, "depth_i", (None, 1, None, None))
    check_shape(z_j, "z_j", (B, 1, H, W))
    check_shape(K, "K", (B, 3, 3))
    check_shape(cam_j_from_cam_i, "cam_j_from_cam_i", (B, 4, 4))
    rays = unproject(torch.ones_like(depth_i), K)  # (B, 3, H, W)
    R, t = cam_j_from_cam_i[:, :3, :3], cam_j_from_cam_i[:, :3, 3]
    a = torch.einsum("bij,bjhw->bihw", R, rays)
    tx, ty, tz = (t[:, k].view(B, 1, 1, 1) for k in range(3))
    z2 = z_j**2
    dx = (a[:, 0:1] * tz - tx * a[:, 2:3]) / z2
    dy = (a[:, 1:2] * tz - ty * a[:, 2:3]) / z2
    fx, s, fy = (K[:, r, c].view(B, 1, 1, 1) for r, c in ((0, 0), (0, 1), (1, 1)))
    return torch.cat([fx * dx + s * dy, fy * dy], 1)


def propagated_flow_std(
    depth_i: torch.Tensor,
    std_i: torch.Tensor,
    K: torch.Tensor,
    cam_j_from_cam_i: torch.Tensor,
    min_depth: float = 1e-6,
) -> torch.Tensor:
    """Std of the flow i -> j implied by depth_i, propagated from std_i at the pose ``cam_j_from_cam_i``
    (σ_u = |∂u/∂d|·σ_d / W, σ_v = |∂v/∂d|·σ_d / H), for :func:`sparse_flow_loss`'s ``flow_std_ij``.

    Args:
        depth_i, std_i: (B, 1, H, W).  K: (B, 3, 3).  cam_j_from_cam_i: (B, 4, 4).
    Returns:
        (B, 2, H, W) std in image-size units; NaN where the depth or std is not finite, the depth is
        <= min_depth or the point lies behind camera j.
    """
    shape = check_shape(depth_i, "depth_i", (None, 1, None, None))
    _check_map(std_i, "std_i", shape)
    check_shape(cam_j_from_cam_i, "cam_j_from_cam_i", (shape[0], 4, 4))
    ok = torch.isfinite(depth_i) & torch.isfinite(std_i) & (depth_i > min_depth)
    d = _safe(depth_i, ok, 1.0)
    T = cam_j_from_cam_i.to(d.dtype)
    _, z_j = flow_from_depth(d, K, T)
    ok = ok & (z_j > min_depth)
    jac = flow_depth_derivative(d, K, T, _safe(z_j, ok, 1.0)) / _image_size(shape, d)
    sigma = (jac * _safe(std_i, ok, 1.0)).abs()
    return torch.where(ok, sigma, torch.full_like(sigma, float("nan")))


def _image_size(shape, like: torch.Tensor) -> torch.Tensor:
    """(1, 2, 1, 1): (W, H), the flow normalisation."""
    return torch.tensor([shape[3], shape[2]], dtype=like.dtype, device=like.device).view(1, 2, 1, 1)


def sparse_flow_loss(
    depth_i: torch.Tensor,
    std_i: torch.Tensor,
    K: torch.Tensor,
    cam_j_from_cam_i: torch.Tensor,
    sparse_flow_ij: torch.Tensor,
    sparse_flow_valid_ij: torch.Tensor,
    eps: float = 1e-8,
    reduction: str = "mean",
    flow_std_floor: float = 1e-3,
    min_depth: float = 1e-6,
    std_pose: torch.Tensor | None = None,
    flow_std_ij: torch.Tensor | None = None,
    min_valid: int = 0,
) -> torch.Tensor:
    """Sparse Flow loss: flow implied by the predicted depth and the relative pose vs SfM flow.

    Flows are normalised by the image size (u by W, v by H).  The flow's std
    comes from the depth std by first-order propagation, σ_u = |∂u/∂d|·σ_d / W
    (closed form, :func:`flow_depth_derivative`), and its variance gets the
    floor ``flow_std_floor²``.  Per point the NLL sums the u and v components
    (a 2-D Gaussian with diagonal covariance).  Points that land behind camera j
    are ignored.

    Args:
        depth_i, std_i: (B, 1, H, W) scaled prediction of frame i.
        K: (B, 3, 3).  cam_j_from_cam_i: (B, 4, 4).
        sparse_flow_ij: (B, 2, H, W) pixel displacement i -> j at the points' pixels in i.
        sparse_flow_valid_ij: (B, 1, H, W) bool.
        std_pose: optional (B, 4, 4) cam_j_from_cam_i at which the depth std is propagated to the flow
            (default: ``cam_j_from_cam_i``); no gradient flows into it.  ∂flow/∂d grows with the baseline, so with
            free poses the log σ² term alone pulls them towards shorter baselines; pose graph optimisation
            passes the initial poses so that it cannot (exact flow at a pose makes it a stationary point).
            Points behind camera j at std_pose are left out.
        flow_std_ij: optional (B, 2, H, W) flow std already propagated (:func:`propagated_flow_std` at std_pose;
            NaN = left out), so that a caller evaluating many poses computes it once; excludes ``std_pose``.
        min_valid: with ``reduction="none"``, NaN for a sample with fewer valid points (0: 0 for none).
    Returns:
        scalar ("mean") or (B,) ("none").
    """
    shape = check_shape(depth_i, "depth_i", (None, 1, None, None))
    if std_pose is not None and flow_std_ij is not None:
        raise ValueError("pass std_pose or flow_std_ij (propagated_flow_std at std_pose), not both")
    if std_pose is not None:
        check_shape(std_pose, "std_pose", (shape[0], 4, 4))
    _check_map(std_i, "std_i", shape)
    _check_map(sparse_flow_ij, "sparse_flow_ij", shape, channels=2)
    _check_map(sparse_flow_valid_ij, "sparse_flow_valid_ij", shape)
    if std_pose is not None:
        flow_std_ij = propagated_flow_std(depth_i, std_i, K, std_pose.detach(), min_depth)
    if flow_std_ij is not None:
        _check_map(flow_std_ij, "flow_std_ij", shape, channels=2)
    valid = (
        sparse_flow_valid_ij.bool()
        & torch.isfinite(sparse_flow_ij).all(1, keepdim=True)
        & torch.isfinite(depth_i)
        & torch.isfinite(std_i)
        & (depth_i > min_depth)
    )
    d = _safe(depth_i, valid, 1.0)
    flow, z_j = flow_from_depth(d, K, cam_j_from_cam_i)
    valid = valid & (z_j > min_depth)
    size = _image_size(shape, d)
    if flow_std_ij is None:
        jac = flow_depth_derivative(d, K, cam_j_from_cam_i, _safe(z_j, valid, 1.0)) / size
        sigma = jac * _safe(std_i, valid, 1.0)
    else:
        valid = valid & torch.isfinite(flow_std_ij).all(1, keepdim=True)
        sigma = _safe(flow_std_ij.to(d.dtype), valid.expand(-1, 2, -1, -1), 1.0)
    var = sigma**2 + flow_std_floor**2
    obs = _safe(sparse_flow_ij, valid.expand(-1, 2, -1, -1), 0.0) / size
    nll = gaussian_nll(obs, flow / size, var, eps).sum(1, keepdim=True)
    nll = _safe(nll, valid, 0.0)  # pixels that fail only the z_j test may be non-finite
    return _reduce(nll, valid, reduction, min_valid)


def sparse_flow_loss_points(
    points_i: torch.Tensor,
    uv_i: torch.Tensor,
    K: torch.Tensor,
    cam_j_from_cam_i: torch.Tensor,
    flow_ij: torch.Tensor,
    flow_std_ij: torch.Tensor,
    valid: torch.Tensor,
    image_size: tuple[int, int],
    eps: float = 1e-8,
    reduction: str = "mean",
    flow_std_floor: float = 1e-3,
    min_depth: float = 1e-6,
) -> torch.Tensor:
    """:func:`sparse_flow_loss` with a given flow std (``flow_std_ij``), evaluated at the sparse points only.

    A dense map is mostly empty (an SfM pair has a few hundred tracks among thousands of pixels); when depth
    and flow std do not change between calls (pose graph optimisation: only poses move) the points can be
    back-projected once and only they moved per call.  Same value as the dense loss on the same points.

    Args:
        points_i: (B, M, 3) frame i's points at its sparse pixels, depth_i · K⁻¹(u, v, 1)ᵀ.
        uv_i: (B, M, 2) those pixels (u = column, v = row, pixel centres at integers).
        K: (B, 3, 3).  cam_j_from_cam_i: (B, 4, 4).
        flow_ij: (B, M, 2) SfM pixel displacement i -> j.
        flow_std_ij: (B, M, 2) flow std in image-size units (:func:`propagated_flow_std` at the points).
        valid: (B, M) bool; padding and unusable points False (their values, NaN included, never count).
        image_size: (H, W) of the images, the flow normalisation.
    Returns:
        scalar ("mean") or (B,) ("none"), as :func:`sparse_flow_loss`.
    """
    B, M, _ = check_shape(points_i, "points_i", (None, None, 3))
    check_shape(uv_i, "uv_i", (B, M, 2))
    check_shape(K, "K", (B, 3, 3))
    check_shape(cam_j_from_cam_i, "cam_j_from_cam_i", (B, 4, 4))
    check_shape(flow_ij, "flow_ij", (B, M, 2))
    check_shape(flow_std_ij, "flow_std_ij", (B, M, 2))
    check_shape(valid, "valid", (B, M))
    H, W = image_size
    ok = (valid.bool() & torch.isfinite(points_i).all(-1) & (points_i[..., 2] > min_depth)
          & torch.isfinite(flow_ij).all(-1) & torch.isfinite(flow_std_ij).all(-1))
    ok2 = ok[..., None].expand(-1, -1, 2)
    X_i = _safe(points_i, ok[..., None].expand(-1, -1, 3), 1.0)
    R, t = cam_j_from_cam_i[:, :3, :3], cam_j_from_cam_i[:, :3, 3]
    uv_j, z_j = project(X_i @ R.transpose(1, 2) + t[:, None], K)
    ok = ok & (z_j > min_depth)
    size = _image_size((B, 1, H, W), X_i).view(2)
    var = _safe(flow_std_ij.to(X_i.dtype), ok2, 1.0) ** 2 + flow_std_floor**2
    obs = _safe(flow_ij.to(X_i.dtype), ok2, 0.0) / size
    nll = gaussian_nll(obs, (uv_j - _safe(uv_i.to(X_i.dtype), ok2, 0.0)) / size, var, eps).sum(-1)
    nll = _safe(nll, ok, 0.0)  # points that fail only the z_j test may be non-finite
    return _reduce(nll[:, None, :, None], ok[:, None, :, None], reduction)
