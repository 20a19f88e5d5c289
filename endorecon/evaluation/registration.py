"""Similarity (Sim(3)) registration of a reconstruction to a reference surface.

The reconstruction's scale is arbitrary, so it is aligned with a similarity
``ref_from_recon``: x_ref = s R x_recon + t.

1. Initialisation, either
   - from the camera trajectory: Umeyama between the reconstruction's camera
     centres and the ground-truth centres of the same frames (plus roll
     hypotheses, and the rotation averaged from the camera orientations, when
     the centres lie nearly on a line), or
   - globally: both point sets are normalised (centroid, RMS radius), then
     FPFH features + RANSAC (Open3D, point-to-point estimation with scaling).
   Several candidates are each refined by a short ICP on a subset; the one
   with the smallest median distance *divided by the scale* wins (in mm alone,
   a candidate that shrinks the reconstruction into a corner could win).
2. Refinement: ICP with scale, written here because Open3D's point-to-plane
   estimation has no scale.  Each iteration takes exact closest points on the
   reference mesh (BVH) with their face normals, rejects outliers whose
   distance exceeds median + k·1.4826·MAD (and an optional absolute cap), and
   takes one damped Gauss-Newton step on Sim(3) for
       sum_i (n_i·(x_i − q_i))² + w² ||x_i − q_i||²,
   i.e. point-to-plane with a small point-to-point term that pins down the
   directions a locally flat surface leaves free.  The update is
   x' = c + e^σ Exp(ω)(x − c) + v about the inlier centroid c, which keeps the
   7 unknowns (σ, ω, v) well conditioned.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
import torch

from endorecon.evaluation.meshes import ReferenceSurface
from endorecon.geometry import so3_exp, umeyama


@dataclass(frozen=True)
class Sim3:
    """A similarity transform ``b_from_a``: x_b = scale · R x_a + t."""

    scale: float
    R: np.ndarray  # (3, 3)
    t: np.ndarray  # (3,)

    @staticmethod
    def identity() -> "Sim3":
        return Sim3(1.0, np.eye(3), np.zeros(3))

    def apply(self, points: np.ndarray) -> np.ndarray:
        """points: (N, 3) -> (N, 3)."""
        return self.scale * points @ self.R.T + self.t

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix [[sR, t], [0, 1]]."""
        M = np.eye(4)
        M[:3, :3] = self.scale * self.R
        M[:3, 3] = self.t
        return M

    def inverse(self) -> "Sim3":
        Rt = self.R.T
        return Sim3(1.0 / self.scale, Rt, -(Rt @ self.t) / self.scale)

    def __matmul__(self, other: "Sim3") -> "Sim3":
        """Composition: (c_from_b @ b_from_a) = c_from_a."""
        return Sim3(self.scale * other.scale, self.R @ other.R, self.scale * self.R @ other.t + self.t)

    def to_dict(self) -> dict:
        return {"scale": float(self.scale), "R": self.R.tolist(), "t": self.t.tolist(), "matrix": self.matrix().tolist()}


@dataclass
class RegistrationResult:
    """``ref_from_recon`` and how it was found."""

    ref_from_recon: Sim3
    init: str  # "trajectory" | "global" | "identity"
    fitness: float  # fraction of points kept as inliers in the last ICP iteration
    inlier_rmse: float  # RMS distance of those inliers (reference units)
    threshold: float  # the last outlier threshold (reference units)
    iterations: int
    converged: bool
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "init": self.init,
            "fitness": float(self.fitness),
            "inlier_rmse": float(self.inlier_rmse),
            "threshold": float(self.threshold),
            "iterations": int(self.iterations),
            "converged": bool(self.converged),
            **self.extra,
        }


def init_from_trajectory(cam_centers: np.ndarray, gt_cam_centers: np.ndarray) -> Sim3:
    """Umeyama similarity mapping reconstructed camera centres onto ground-truth ones.

    Args:
        cam_centers: (N, 3) camera centres of the reconstruction (its own units), N >= 3.
        gt_cam_centers: (N, 3) ground-truth centres of the same frames (reference units).
    """

    cam_centers = np.asarray(cam_centers, dtype=np.float64)
    gt_cam_centers = np.asarray(gt_cam_centers, dtype=np.float64)
    if cam_centers.ndim != 2 or cam_centers.shape[1] != 3 or cam_centers.shape != gt_cam_centers.shape:
        raise ValueError(f"camera centres must both be (N, 3), got {cam_centers.shape} and {gt_cam_centers.shape}")
    if len(cam_centers) < 3:
        raise ValueError(f"need at least 3 camera centres for a similarity, got {len(cam_centers)}")
    s, R, t = umeyama(cam_centers, gt_cam_centers, with_scale=True)
    return Sim3(float(s), np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64))


def trajectory_candidates(
    cam_centers: np.ndarray,
    gt_cam_centers: np.ndarray,
    cam_rotations: np.ndarray | None = None,
    gt_cam_rotations: np.ndarray | None = None,
    n_roll: int = 8,
    collinear_ratio: float = 0.05,
) -> list[Sim3]:
    """Initial ``ref_from_recon`` guesses from matching camera trajectories.

    The first guess is Umeyama on the centres.  An endoscope often moves along
    a nearly straight line, which leaves the roll about that line free; when
    the centres' second principal extent is below ``collinear_ratio`` of the
    first, more guesses are added: the rotation averaged from the camera
    orientations (when given) and ``n_roll`` rolls of the Umeyama guess about
    the line.

    Args:
        cam_centers, gt_cam_centers: (K, 3) centres of the same K frames.
        cam_rotations, gt_cam_rotations: optional (K, 3, 3) ``cam_from_world`` rotations.
    """
    T0 = init_from_trajectory(cam_centers, gt_cam_centers)
    gt = np.asarray(gt_cam_centers, dtype=np.float64)
    sv = np.linalg.svd(gt - gt.mean(0), compute_uv=False)
    if sv[1] >= collinear_ratio * max(sv[0], 1e-300):
        return [T0]
    out = [T0]
    if cam_rotations is not None and gt_cam_rotations is not None:
        # cam_from_recon = cam_from_ref @ ref_from_recon  =>  R = R_gtᵀ R_rec, averaged on SO(3).
        Rs = np.einsum("kji,kjl->kil", np.asarray(gt_cam_rotations, float), np.asarray(cam_rotations, float))
        U, _, Vt = np.linalg.svd(Rs.sum(0))
        R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
        rec = np.asarray(cam_centers, dtype=np.float64)
        rc, gc = (rec - rec.mean(0)) @ R.T, gt - gt.mean(0)
        s = float((rc * gc).sum() / max((rc * rc).sum(), 1e-300))
        if s > 0:
            out.append(Sim3(s, R, gt.mean(0) - s * R @ rec.mean(0)))
    axis = np.linalg.svd(gt - gt.mean(0), full_matrices=False)[2][0]
    c = gt.mean(0)
    for k in range(1, n_roll):
        Ru = so3_exp(torch.from_numpy(axis * (2 * np.pi * k / n_roll))[None])[0].numpy()
        out.append(Sim3(1.0, Ru, c - Ru @ c) @ T0)
    return out


def _normalise(points: np.ndarray) -> tuple[np.ndarray, float]:
    c = points.mean(0)
    r = float(np.sqrt(((points - c) ** 2).sum(1).mean()))
    return c, r


def _fpfh(points: np.ndarray, voxel: float):
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd = pcd.voxel_down_sample(voxel)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5 * voxel, max_nn=30))
    # Orient towards the centroid so both clouds agree on the sign (feature histograms depend on it).
    pcd.orient_normals_towards_camera_location(np.asarray(pcd.points).mean(0))
    feat = o3d.pipelines.registration.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100)
    )
    return pcd, feat


def global_registration(
    src_points: np.ndarray,
    ref_points: np.ndarray,
    seed: int = 0,
    voxel_frac: float = 0.1,
    trials: int = 1,
    max_iterations: int = 100000,
) -> list[tuple[Sim3, float]]:
    """FPFH + RANSAC similarity from ``src_points`` to ``ref_points`` (no initial guess needed).

    Scale is first normalised by each cloud's RMS radius about its centroid,
    which assumes the two cover roughly the same part of the surface; RANSAC
    then estimates the remaining similarity (with scaling).

    Args:
        src_points: (N, 3) reconstruction samples.  ref_points: (M, 3) reference samples.
        voxel_frac: FPFH voxel size as a fraction of the normalised RMS radius.
        trials: RANSAC runs (seeds seed, seed+1, ...) on the same features.
    Returns:
        one (ref_from_src, RANSAC fitness) per trial.
    """
    c_s, r_s = _normalise(src_points)
    c_r, r_r = _normalise(ref_points)
    src_pcd, src_f = _fpfh((src_points - c_s) / r_s, voxel_frac)
    ref_pcd, ref_f = _fpfh((ref_points - c_r) / r_r, voxel_frac)
    reg = o3d.pipelines.registration
    dist = 1.5 * voxel_frac
    # x_ref = r_r (s_n R_n (x − c_s)/r_s + t_n) + c_r
    ref_from_norm = Sim3(r_r, np.eye(3), c_r)
    norm_from_src = Sim3(1.0 / r_s, np.eye(3), -c_s / r_s)
    out = []
    for k in range(max(1, trials)):
        o3d.utility.random.seed(int(seed + k))
        res = reg.registration_ransac_based_on_feature_matching(
            src_pcd,
            ref_pcd,
            src_f,
            ref_f,
            True,  # mutual filter
            dist,
            reg.TransformationEstimationPointToPoint(with_scaling=True),
            3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(dist)],
            reg.RANSACConvergenceCriteria(max_iterations, 0.999),
        )
        M = np.asarray(res.transformation)
        s_n = float(np.cbrt(np.linalg.det(M[:3, :3])))
        if not np.isfinite(s_n) or s_n <= 0:  # RANSAC found nothing: identity in normalised frames
            norm_T = Sim3.identity()
        else:
            norm_T = Sim3(s_n, M[:3, :3] / s_n, M[:3, 3].copy())
        out.append((ref_from_norm @ norm_T @ norm_from_src, float(res.fitness)))
    return out


def icp_sim3(
    src_points: np.ndarray,
    surface: ReferenceSurface,
    init: Sim3,
    max_iter: int = 60,
    reject_k: float = 3.0,
    max_dist: float | None = None,
    point_weight: float = 0.1,
    damping: float = 1e-6,
    tol: float = 1e-5,
    min_threshold_frac: float = 1e-3,
    scale_slack: float | None = None,
    max_scale_step: float = 0.05,
) -> RegistrationResult:
    """Point-to-plane ICP with scale against a mesh (see module docstring).

    Args:
        src_points: (N, 3) points of the reconstruction (its units).
        surface: the reference mesh.
        init: initial ``ref_from_recon``.
        reject_k: outlier threshold median + k·1.4826·MAD of the closest-point distances.
        max_dist: optional absolute cap on that threshold (reference units).
        point_weight: weight w of the point-to-point term.
        damping: Levenberg-Marquardt factor on diag(JᵀJ).
        tol: stop when the step (σ, ω, v / RMS radius) is below this.  With noisy data the
            steps settle at ~1e-6..1e-5 (points hopping between faces of the mesh), so a smaller
            tolerance only burns iterations; a zero-residual fit converges quadratically well past it.
        min_threshold_frac: floor of the outlier threshold, as a fraction of the RMS radius of
            the registered points (without it a perfect fit would reject half its points as noise).
        scale_slack: keep the scale within [s0 / slack, s0 · slack] of the initial scale s0.  A free
            scale has a degenerate optimum: shrinking the reconstruction onto a patch of the surface
            drives every distance (and, with outlier rejection, the inlier set) to zero.
        max_scale_step: bound on |log scale change| per iteration, for the same reason.
    """
    if src_points.ndim != 2 or src_points.shape[1] != 3 or len(src_points) < 7:
        raise ValueError(f"src_points must be (N>=7, 3), got {tuple(src_points.shape)}")
    if not np.isfinite(src_points).all():  # a NaN median made every point an outlier: init returned as is
        raise ValueError(f"src_points has {int((~np.isfinite(src_points).all(1)).sum())} non-finite row(s)")
    if not (np.isfinite(init.scale) and init.scale > 0 and np.isfinite(init.R).all() and np.isfinite(init.t).all()):
        raise ValueError(f"init must be a finite similarity with scale > 0, got scale {init.scale}")
    T = init
    s_lo, s_hi = (init.scale / scale_slack, init.scale * scale_slack) if scale_slack else (0.0, np.inf)
    converged = False
    it = 0
    inl = np.ones(len(src_points), bool)
    thr = np.inf
    for it in range(1, max_iter + 1):
        x = T.apply(src_points)
        q, n = surface.closest(x)
        d = np.linalg.norm(x - q, axis=1)
        med = np.median(d)
        thr = med + reject_k * 1.4826 * np.median(np.abs(d - med))
        thr = max(thr, min_threshold_frac * float(np.sqrt(((x - x.mean(0)) ** 2).sum(1).mean())))
        if max_dist is not None:
            thr = min(thr, max_dist)
        inl = d <= thr
        if inl.sum() < 7:
            break
        sigma, w, v, scale_ref = _gauss_newton_step(x[inl], q[inl], n[inl], point_weight, damping)
        c = x[inl].mean(0)
        dR = so3_exp(torch.from_numpy(w)[None])[0].numpy()
        sigma = float(np.clip(sigma, -max_scale_step, max_scale_step))
        sigma = float(np.clip(sigma, np.log(s_lo / T.scale) if s_lo > 0 else -np.inf, np.log(s_hi / T.scale)))
        es = float(np.exp(sigma))
        # x' = c + e^σ dR (x − c) + v, composed onto x = sR p + t.
        T = Sim3(es * T.scale, dR @ T.R, es * dR @ (T.t - c) + c + v)
        step = max(abs(sigma), float(np.linalg.norm(w)), float(np.linalg.norm(v)) / scale_ref)
        if step < tol:
            converged = True
            break
    x = T.apply(src_points)
    d = surface.distance(x)
    inl = d <= thr
    rmse = float(np.sqrt((d[inl] ** 2).mean())) if inl.any() else float("nan")
    return RegistrationResult(
        T, "identity", float(inl.mean()), rmse, float(thr), it, converged, {"median_distance": float(np.median(d))}
    )


def _gauss_newton_step(x, q, n, point_weight, damping):
    """One damped GN step for the Sim(3) increment (σ, ω, v) about the centroid of x.  x, q, n: (M, 3)."""
    y = x - x.mean(0)
    scale_ref = max(float(np.sqrt((y**2).sum(1).mean())), 1e-12)
    e = x - q
    # Point-to-plane rows: r = n·(x − q); ∂/∂σ = n·y, ∂/∂ω = y × n, ∂/∂v = n.
    r_pl = (e * n).sum(1)
    J_pl = np.concatenate([(n * y).sum(1, keepdims=True), np.cross(y, n), n], axis=1)
    # Point-to-point rows: r = x − q; ∂/∂σ = y, ∂/∂ω = −[y]×, ∂/∂v = I (stacked per point as (M, 3, 7)).
    M = len(y)
    J_pt = np.zeros((M, 3, 7))
    J_pt[:, :, 0] = y
    J_pt[:, 0, 2], J_pt[:, 0, 3] = y[:, 2], -y[:, 1]
    J_pt[:, 1, 1], J_pt[:, 1, 3] = -y[:, 2], y[:, 0]
    J_pt[:, 2, 1], J_pt[:, 2, 2] = y[:, 1], -y[:, 0]
    J_pt[:, 0, 4] = J_pt[:, 1, 5] = J_pt[:, 2, 6] = 1.0
    J_pt = J_pt.reshape(-1, 7)
    w2 = point_weight**2
    H = J_pl.T @ J_pl + w2 * (J_pt.T @ J_pt)
    g = J_pl.T @ r_pl + w2 * (J_pt.T @ e.reshape(-1))
    H = H + damping * np.diag(np.maximum(np.diag(H), 1e-12))
    d = -np.linalg.solve(H, g)
    return float(d[0]), d[1:4].copy(), d[4:7].copy(), scale_ref


INITS = ("auto", "trajectory", "global", "identity")  # register()'s initialisations


def register(
    src_points: np.ndarray,
    surface: ReferenceSurface,
    ref_points: np.ndarray | None = None,
    cam_centers: np.ndarray | None = None,
    gt_cam_centers: np.ndarray | None = None,
    cam_rotations: np.ndarray | None = None,
    gt_cam_rotations: np.ndarray | None = None,
    init: str = "auto",
    seed: int = 0,
    global_trials: int = 5,
    global_voxel_frac: float = 0.1,
    global_src_points: np.ndarray | None = None,
    select_points: int = 4000,
    **icp_kwargs,
) -> RegistrationResult:
    """Sim(3) ``ref_from_recon``: initialise (trajectory / global / identity), then ICP with scale.

    Args:
        src_points: (N, 3) samples of the reconstruction.
        surface: the reference mesh.
        ref_points: (M, 3) samples of the reference (needed for the global initialisation).
        cam_centers, gt_cam_centers: (K, 3) matching camera centres (for the trajectory initialisation).
        cam_rotations, gt_cam_rotations: optional (K, 3, 3) matching ``cam_from_world`` rotations
            (they fix the roll when the trajectory is nearly a straight line).
        init: "auto" (trajectory when centres are given, else global), "trajectory", "global" or "identity".
        global_trials: RANSAC runs with different seeds; the one with the best ICP result is kept.
        global_src_points: optional denser (N', 3) samples of the reconstruction for the FPFH
            features (FPFH needs a dense cloud; defaults to ``src_points``).
        select_points: size of the subset on which the candidates are compared.
        icp_kwargs: passed to :func:`icp_sim3`.
    """
    if init == "auto":
        init = "trajectory" if cam_centers is not None and gt_cam_centers is not None else "global"
    if init == "trajectory":
        if cam_centers is None or gt_cam_centers is None:
            raise ValueError("init='trajectory' needs cam_centers and gt_cam_centers")
        cands = trajectory_candidates(cam_centers, gt_cam_centers, cam_rotations, gt_cam_rotations)
        # The trajectory fixes the scale well: ICP may refine it by 25 % at most.
        icp_kwargs = {"scale_slack": 1.25, **icp_kwargs}
        return _best_of(src_points, surface, [(T, None) for T in cands], "trajectory", seed, select_points, icp_kwargs)
    if init == "identity":
        return icp_sim3(src_points, surface, Sim3.identity(), **icp_kwargs)
    if init != "global":
        raise ValueError(f"unknown init '{init}' ({', '.join(INITS)})")
    if ref_points is None:
        raise ValueError("init='global' needs ref_points")
    fpfh_src = src_points if global_src_points is None else global_src_points
    candidates = global_registration(fpfh_src, ref_points, seed, global_voxel_frac, global_trials)
    icp_kwargs = {"scale_slack": 2.0, **icp_kwargs}
    return _best_of(src_points, surface, candidates, "global", seed, select_points, icp_kwargs)


def _best_of(src_points, surface, candidates, init, seed, select_points, icp_kwargs) -> RegistrationResult:
    """Refine the candidate whose short ICP on a subset ends closest to the surface.

    Criterion: the median distance (robust to the part of a reconstruction that the reference does
    not cover) divided by the scale, i.e. measured in the reconstruction's own units.
    """
    best = None
    if len(candidates) > 1:
        sub = src_points[np.random.default_rng(seed).permutation(len(src_points))[:select_points]]
        for k, (T0, fit) in enumerate(candidates):
            trial = icp_sim3(sub, surface, T0, **{**icp_kwargs, "max_iter": min(20, icp_kwargs.get("max_iter", 20))})
            # In the reconstruction's units (÷ scale): a candidate that shrinks the reconstruction
            # into a corner of the reference must not win by having small distances in mm.
            key = trial.extra["median_distance"] / trial.ref_from_recon.scale
            if best is None or key < best[0]:
                best = (key, trial.ref_from_recon, k, fit)
    else:
        best = (None, candidates[0][0], 0, candidates[0][1])
    res = icp_sim3(src_points, surface, best[1], **icp_kwargs)
    res.init = init
    res.extra.update(candidate=best[2], n_candidates=len(candidates))
    if best[3] is not None:
        res.extra["ransac_fitness"] = best[3]
    return res
