"""Dense pose graph optimisation: refine every frame's pose against the network's dense depth.

Each registered frame k gets a twist xi_k, and its pose is
``cam_k_from_world = se3_exp(xi_k) @ cam_k_from_world_init`` (xi_k = 0 at the
SfM initialisation).  The first registered frame is fixed, so every pose is
optimised relative to it (which removes the gauge freedom; the scale is fixed
by the depths).  Edges join frame k to k+o for ``o`` in ``neighbors`` (5, 6, 7,
8), optionally in both directions, and each edge costs

    w_flow · sparse_flow_loss(depth_k, std_k, T_{j←k}, SfM flow k→j)
    + w_consistency · depth_consistency_loss(depth_k, std_k, depth_j, std_j, T_{j←k})

(:mod:`endorecon.losses`, per-edge means); the objective is the mean over
edges.  Depths and stds are the network's, detached: only poses move.  With
``normalize_depth`` depths, stds and translations are divided by the median
depth while optimising, so ``lr`` is in median-depth units whatever the
sequence's units.  Unregistered frames (NaN pose) take no part and stay NaN.

The stds enter each NLL as they are carried between the frames at the initial
(SfM) poses (``freeze_std``, the losses' ``std_pose``): propagated at the free
poses, the log-variance terms alone would pull the poses towards shorter
baselines (on the test scene with exact data, 0.07 deg off the true poses).
Being constants, they are computed once per edge before optimising (the
consistency stds only while ``edges x H x W`` values fit ``std_cache_mb``).
The default optimiser is L-BFGS (strong Wolfe line search with up to
``line_search_evals`` evaluations), restarted with a halved step when a line
search stalls.  The objective is first-order only and
the sparse-flow NLL is sharp (flow std of a fraction of a pixel), so
rotation/translation trade-offs along the optical axis converge slowly: on the
12-frame test scene 60 iterations cut the pose error ~5x with the reference
frame exact, but only ~1.7x/1.25x (rotation/translation) when the reference
frame itself carries the same noise.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable, Mapping

import numpy as np
import torch

from endorecon.geometry import invert_pose, pixel_grid, rotation_angle_deg, se3_exp, unproject
from endorecon.geometry._checks import check_shape
from endorecon.losses import (
    carried_std,
    depth_consistency_loss,
    propagated_flow_std,
    sparse_flow_loss,
    sparse_flow_loss_points,
)

DEFAULTS = {
    "neighbors": [5, 6, 7, 8],
    "bidirectional": True,
    "w_flow": 100.0,
    "w_consistency": 1.0,
    "optimizer": "lbfgs",
    "iterations": 60,
    "lr": 1.0,
    "line_search_evals": 10,
    "freeze_std": True,
    "flow_at_points": True,
    "std_cache_mb": 512,
    "normalize_depth": True,
    "edge_chunk": 32,
    "min_flow_points": 3,
    "progress": True,
}

SparseFlowFn = Callable[[int, int], "tuple[torch.Tensor, torch.Tensor] | None"]


def _get(cfg, key):
    if cfg is not None and key in cfg and cfg[key] is not None:
        return cfg[key]
    return DEFAULTS[key]


@dataclasses.dataclass
class PGOResult:
    """Refined poses and how the optimisation went.

    Attributes:
        cam_from_world: (N, 4, 4) refined poses (NaN rows stay NaN), input units.
        history: objective per iteration (normalised units).
        update_rotation_deg: (N,) rotation of each frame's update (NaN: unregistered).
        update_translation: (N,) camera-centre displacement of each frame, input units.
        loss_before, loss_after: objective at the initial and the refined poses.
        edges: the (i, j) edges used.
        fixed_frame: the frame held fixed.
    """

    cam_from_world: torch.Tensor
    history: list[float]
    update_rotation_deg: torch.Tensor
    update_translation: torch.Tensor
    loss_before: float
    loss_after: float
    edges: list[tuple[int, int]]
    fixed_frame: int

    def summary(self) -> str:
        r = self.update_rotation_deg[torch.isfinite(self.update_rotation_deg)]
        t = self.update_translation[torch.isfinite(self.update_translation)]
        return (
            f"PGO: {len(self.edges)} edges, loss {self.loss_before:.4g} -> {self.loss_after:.4g}; "
            f"updates: rotation median {float(r.median()):.3g}° max {float(r.max()):.3g}°, "
            f"translation median {float(t.median()):.3g} max {float(t.max()):.3g}"
        )


class _Edges:
    """Edge list with its sparse flows stored as (pixel index, flow) pairs, densified per chunk.

    With frozen stds (:meth:`freeze_stds`) it also holds each edge's stds carried at the initial poses: the
    flow std at the sparse pixels, and (when it fits the memory budget) the consistency term's carried
    std_j, so that no objective evaluation recomputes these constants."""

    def __init__(self, edges, flows, H, W, dtype, device):
        self.edges = edges
        self.flows = flows  # per edge: None or (idx (M,), flow (M, 2))
        self.H, self.W, self.dtype, self.device = H, W, dtype, device
        self.flow_std = None  # per edge: None or (M, 2) flow std at idx
        self.cons_std = None  # (n_edges, 1, H, W) carried std_j, or None: carried per evaluation
        self.points = None  # (points_i, uv_i, flow, flow_std, valid), each (n_edges, M, .), padded; or None

    def dense(self, ks):
        """Flows (B, 2, H, W), valid (B, 1, H, W), has-flow (B,) and, if frozen, flow stds (B, 2, H, W)."""
        B = len(ks)
        flow = torch.zeros(B, 2, self.H * self.W, dtype=self.dtype, device=self.device)
        valid = torch.zeros(B, 1, self.H * self.W, dtype=torch.bool, device=self.device)
        has = torch.zeros(B, dtype=torch.bool, device=self.device)
        fstd = None if self.flow_std is None else torch.full_like(flow, float("nan"))
        for b, k in enumerate(ks):
            if self.flows[k] is not None:
                idx, f = self.flows[k]
                flow[b, :, idx] = f.T
                valid[b, 0, idx] = True
                has[b] = True
                if fstd is not None:
                    fstd[b, :, idx] = self.flow_std[k].T
        shape = (B, 2, self.H, self.W)
        return flow.view(shape), valid.view(B, 1, self.H, self.W), has, None if fstd is None else fstd.view(shape)

    def freeze_stds(self, T0, depth, std, K, mask, chunk: int, cache_mb: float, at_points: bool = False) -> None:
        """Carry the stds of every edge at the initial poses ``T0`` once (see :func:`_edge_losses`); with
        ``at_points`` also gather each edge's sparse points (:meth:`_gather_points`)."""
        n = len(self.edges)
        cache_cons = n * self.H * self.W * depth.element_size() <= cache_mb * 2**20
        self.flow_std = [None] * n
        cons = [] if cache_cons else None
        points = [None] * n
        with torch.no_grad():
            for s in range(0, n, chunk):
                ks = list(range(s, min(s + chunk, n)))
                ii, jj, T_ji0 = self._pairs(ks, T0)
                m = mask[None].expand(len(ks), -1, -1, -1)
                if cache_cons:
                    cons.append(carried_std(depth[ii], std[ii], depth[jj], std[jj], K[ii], T_ji0, m, m))
                fs = propagated_flow_std(depth[ii], std[ii], K[ii], T_ji0).flatten(2)
                X = unproject(depth[ii], K[ii]).flatten(2) if at_points else None
                for b, k in enumerate(ks):
                    if self.flows[k] is not None:
                        idx = self.flows[k][0]
                        self.flow_std[k] = fs[b][:, idx].T.contiguous()
                        if at_points:  # unusable points (non-finite depth or std) the loss itself leaves out
                            points[k] = X[b][:, idx].T
        self.cons_std = torch.cat(cons) if cache_cons else None
        if at_points:
            self.points = self._gather_points(points)

    def _gather_points(self, points):
        """Per-edge points (M, 3) -> padded (n_edges, M_max, .) tensors; padding is invalid."""
        n, m_max = len(self.edges), max([1] + [len(p) for p in points if p is not None])
        X = torch.ones(n, m_max, 3, dtype=self.dtype, device=self.device)
        uv = torch.zeros(n, m_max, 2, dtype=self.dtype, device=self.device)
        flow = torch.zeros_like(uv)
        fstd = torch.ones_like(uv)
        ok = torch.zeros(n, m_max, dtype=torch.bool, device=self.device)
        grid = pixel_grid(self.H, self.W, self.device, self.dtype).reshape(-1, 2)
        for k, p in enumerate(points):
            if p is None:
                continue
            idx, f = self.flows[k]
            M = len(idx)
            X[k, :M], ok[k, :M] = p, True
            uv[k, :M], flow[k, :M], fstd[k, :M] = grid[idx], f, self.flow_std[k]
        return X, uv, flow, fstd, ok

    def _pairs(self, ks, T0):
        ii = [self.edges[k][0] for k in ks]
        jj = [self.edges[k][1] for k in ks]
        return ii, jj, T0[jj] @ invert_pose(T0[ii])


def _edge_losses(xi, T0, depth, std, K, mask, E: _Edges, ks, w_flow, w_cons):
    """Weighted per-edge objective for the edges ``ks``: (len(ks),).

    When ``E`` has frozen stds (:meth:`_Edges.freeze_stds`), the stds are those carried between the frames
    at the initial poses ``T0`` (the losses' ``std_pose``), so that the objective's log σ² terms are constants
    of the poses; else they are carried at the current poses."""
    ii, jj, T_ji0 = E._pairs(ks, T0)
    T_i = se3_exp(xi[ii]) @ T0[ii]
    T_j = se3_exp(xi[jj]) @ T0[jj]
    T_ji = T_j @ invert_pose(T_i)
    Kb = K[ii]
    m = mask[None].expand(len(ks), -1, -1, -1)
    frozen = E.flow_std is not None
    if frozen and E.cons_std is not None:
        carried = {"std_j_in_i": E.cons_std[ks]}
    else:
        carried = {"std_pose": T_ji0} if frozen else {}
    cons = depth_consistency_loss(
        depth[ii], std[ii], depth[jj], std[jj], Kb, T_ji, m, reduction="none", mask_j=m, **carried
    )
    out = w_cons * cons
    if E.points is not None:  # the sparse points only; an edge without flow has none valid and costs 0
        X, uv, flow, flow_std, ok = (t[ks] for t in E.points)
        return out + w_flow * sparse_flow_loss_points(X, uv, Kb, T_ji, flow, flow_std, ok, (E.H, E.W), reduction="none")
    flow, valid, has, flow_std = E.dense(ks)
    if has.any():
        fl = sparse_flow_loss(depth[ii], std[ii], Kb, T_ji, flow, valid & m, reduction="none", flow_std_ij=flow_std)
        out = out + w_flow * torch.where(has, fl, torch.zeros_like(fl))
    return out


def optimize_poses(
    depth: torch.Tensor,
    std: torch.Tensor,
    K: torch.Tensor,
    cam_from_world_init: torch.Tensor,
    mask: torch.Tensor,
    sparse_flow_fn: SparseFlowFn,
    cfg: Mapping | None = None,
) -> PGOResult:
    """Refine all poses relative to the first registered frame (see the module docstring).

    Args:
        depth: (N, 1, H, W) network depth (detached here).
        std: (N, 1, H, W) network std (detached here).
        K: (3, 3) or (N, 3, 3) pixel-centre intrinsics.
        cam_from_world_init: (N, 4, 4) SfM poses; NaN rows = unregistered.
        mask: (1, H, W) bool valid-pixel mask.
        sparse_flow_fn: ``(i, j) -> (flow (2, H, W) pixels i->j, valid (1, H, W))`` or None.
        cfg: keys of ``conf/pgo/default.yaml`` (missing keys take those defaults).
    Returns:
        :class:`PGOResult`.
    """
    N, _, H, W = check_shape(depth, "depth", (None, 1, None, None))
    check_shape(std, "std", (N, 1, H, W))
    check_shape(cam_from_world_init, "cam_from_world_init", (N, 4, 4))
    check_shape(mask, "mask", (1, H, W))
    if K.shape == (3, 3):
        K = K.expand(N, 3, 3)
    check_shape(K, "K", (N, 3, 3))
    dt, dev = depth.dtype, depth.device
    opt_name = str(_get(cfg, "optimizer")).lower()
    if opt_name not in ("adam", "lbfgs"):
        raise ValueError(f"pgo.optimizer must be 'adam' or 'lbfgs', got {opt_name!r}")
    iterations = int(_get(cfg, "iterations"))
    lr = float(_get(cfg, "lr"))
    w_flow, w_cons = float(_get(cfg, "w_flow")), float(_get(cfg, "w_consistency"))
    chunk = max(1, int(_get(cfg, "edge_chunk")))
    freeze_std = bool(_get(cfg, "freeze_std"))
    min_pts = int(_get(cfg, "min_flow_points"))

    registered = torch.isfinite(cam_from_world_init.flatten(1)).all(1).tolist()
    reg = [k for k in range(N) if registered[k]]
    if len(reg) < 2:
        raise ValueError(f"pose graph optimisation needs at least 2 registered frames, got {len(reg)}")
    fixed = reg[0]
    mask_b = mask.bool().to(dev)
    depth = depth.detach()
    std = std.detach()
    scale = 1.0
    if _get(cfg, "normalize_depth"):
        d = depth[reg][mask_b[None].expand(len(reg), -1, -1, -1)]
        d = d[torch.isfinite(d) & (d > 0)]
        if len(d) == 0:
            raise ValueError("no valid depth inside the mask")
        scale = float(d[:: max(1, len(d) // 1_000_000)].median())
    depth_n, std_n = depth / scale, std / scale
    T0 = cam_from_world_init.to(device=dev, dtype=dt).clone()
    T0[~torch.tensor(registered, device=dev)] = torch.eye(4, dtype=dt, device=dev)  # placeholders, never used
    T0[:, :3, 3] /= scale
    Kd = K.to(device=dev, dtype=dt)

    pairs = [(i, i + int(o)) for i in reg for o in _get(cfg, "neighbors") if 0 <= i + int(o) < N and registered[i + int(o)]]
    if _get(cfg, "bidirectional"):
        pairs = pairs + [(j, i) for i, j in pairs]
    if not pairs:
        raise ValueError(f"no edges: {len(reg)} registered frames and neighbours {list(_get(cfg, 'neighbors'))}")
    flows = []
    for i, j in pairs:
        got = sparse_flow_fn(i, j)
        if got is None:
            flows.append(None)
            continue
        f, v = got
        check_shape(f, "sparse flow", (2, H, W))
        check_shape(v, "sparse flow valid", (1, H, W))
        idx = torch.nonzero((v.bool().to(dev) & mask_b).flatten()).flatten()
        flows.append((idx, f.to(device=dev, dtype=dt).flatten(1)[:, idx].T) if len(idx) >= min_pts else None)
    E = _Edges(pairs, flows, H, W, dt, dev)
    n_e = len(pairs)
    if freeze_std:
        E.freeze_stds(T0, depth_n, std_n, Kd, mask_b, chunk, float(_get(cfg, "std_cache_mb")),
                      at_points=bool(_get(cfg, "flow_at_points")))

    free = torch.tensor([registered[k] and k != fixed for k in range(N)], device=dev)[:, None].to(dt)
    xi = torch.zeros(N, 6, dtype=dt, device=dev, requires_grad=True)

    def objective(backward: bool) -> float:
        total = 0.0
        for s in range(0, n_e, chunk):
            ks = list(range(s, min(s + chunk, n_e)))
            loss = _edge_losses(xi * free, T0, depth_n, std_n, Kd, mask_b, E, ks, w_flow, w_cons).sum() / n_e
            if backward:
                loss.backward()  # per chunk: memory bounded by edge_chunk
            total += float(loss.detach())
        return total

    with torch.no_grad():
        loss_before = objective(False)
    # torch's default max_eval is max_iter * 5 // 4 = 1 for max_iter=1: the line search would then get no
    # evaluation beyond its first trial step, and a step that overshoots is undone, not shortened (on the real
    # sinus clip every iteration was, and PGO left every pose exactly where SfM put it)
    ls_evals = int(_get(cfg, "line_search_evals"))
    if ls_evals < 1:
        raise ValueError(f"pgo.line_search_evals must be >= 1, got {ls_evals}")

    def make_lbfgs(step):
        return torch.optim.LBFGS([xi], lr=step, max_iter=1, max_eval=1 + ls_evals, history_size=20,
                                 line_search_fn="strong_wolfe")

    if opt_name == "adam":
        opt = torch.optim.Adam([xi], lr=lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, iterations), eta_min=0.05 * lr)
    else:
        opt = make_lbfgs(lr)
        sched = None

    def closure():
        opt.zero_grad()
        return torch.tensor(objective(True), dtype=dt)

    history: list[float] = []
    progress = _progress(bool(_get(cfg, "progress")))
    with progress:
        task = progress.add_task("PGO", total=iterations, loss=loss_before)
        for _ in range(iterations):
            if opt_name == "lbfgs":
                xi_before = xi.detach().clone()
                value = float(opt.step(closure))  # the loss at the start of the step
                if torch.equal(xi.detach(), xi_before):
                    # A failed line search leaves L-BFGS stuck at one point: restart it with a smaller step
                    # now (comparing the returned losses, start-of-step values, saw it one iteration late).
                    lr *= 0.5
                    opt = make_lbfgs(lr)
            else:
                value = _adam_step(opt, closure)
            if sched is not None:
                sched.step()
            history.append(value)
            progress.update(task, advance=1, loss=value)

    with torch.no_grad():
        loss_after = objective(False)
        update = se3_exp(xi * free)
        T_n = update @ T0
        rot = rotation_angle_deg(update[:, :3, :3])
        # Camera-centre displacement, c = -Rᵀt, in input units.
        c0 = -(T0[:, :3, :3].transpose(1, 2) @ T0[:, :3, 3:])[..., 0]
        c1 = -(T_n[:, :3, :3].transpose(1, 2) @ T_n[:, :3, 3:])[..., 0]
        trans = (c1 - c0).norm(dim=1) * scale
        # Apply the update (translation back in input units) to the input poses in their own precision,
        # so that the fixed frame is returned bit-exact.
        U = update.to(device=cam_from_world_init.device, dtype=cam_from_world_init.dtype)
        U[:, :3, 3] *= scale
        T_out = cam_from_world_init.clone()
        reg_t = torch.tensor(registered, device=T_out.device)
        T_out[reg_t] = U[reg_t] @ cam_from_world_init[reg_t]
        nan = torch.tensor(float("nan"), dtype=dt, device=dev)
        rot = torch.where(reg_t.to(dev), rot, nan)
        trans = torch.where(reg_t.to(dev), trans, nan)
    return PGOResult(T_out, history, rot.cpu(), trans.cpu(), loss_before, loss_after, pairs, fixed)


def _adam_step(opt, closure) -> float:
    value = closure()
    opt.step()
    return float(value)


def _progress(enabled: bool):
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    return Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
        TextColumn("loss {task.fields[loss]:.4g}"), TimeElapsedColumn(), TimeRemainingColumn(),
        disable=not enabled, transient=True,
    )


def run(
    cfg: Mapping | None,
    names: list[str],
    depth: torch.Tensor,
    std: torch.Tensor,
    K: torch.Tensor,
    cam_from_world_init: torch.Tensor,
    mask: torch.Tensor,
    sparse_flow_fn: SparseFlowFn,
    out_dir: str | Path,
) -> Path:
    """Stage entry: write refined poses to ``<out_dir>/poses.txt`` (skipped when it exists)."""
    from endorecon.data.sequence import write_poses_txt

    path = Path(out_dir) / "poses.txt"
    if path.is_file():
        return path
    res = optimize_poses(depth, std, K, cam_from_world_init, mask, sparse_flow_fn, cfg)
    return write_poses_txt(path, names, np.asarray(res.cam_from_world.detach().cpu(), dtype=np.float64))
