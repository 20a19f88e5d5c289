"""The evaluate task: ``python evaluate.py mesh=<ply> reference=<ply> [trajectory=<poses.txt> gt_trajectory=<poses.txt>]``.

Registers the reconstruction to the reference surface with a similarity,
writes ``metrics.json``, ``residual_heatmap.png``, ``residual_histogram.png``
and ``residuals.npz`` into the run dir, and prints a table of the residuals.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from endorecon.data.sequence import read_poses_txt
from endorecon.evaluation.evaluate import evaluate_mesh
from endorecon.evaluation.registration import INITS
from endorecon.geometry import camera_centers
from endorecon.utils.errors import InputError

log = logging.getLogger(__name__)


def load_trajectories(poses_path: str | Path, gt_poses_path: str | Path) -> tuple[np.ndarray, ...]:
    """Camera centres and rotations of the frames present (and finite) in both pose files, matched by name.

    Returns:
        (cam_centers (K, 3), gt_cam_centers (K, 3), cam_rotations (K, 3, 3), gt_cam_rotations (K, 3, 3)).
    Raises:
        InputError: a file is missing/malformed, or fewer than 3 frames are shared.
    """
    names, T = read_poses_txt(poses_path)
    gt_names, T_gt = read_poses_txt(gt_poses_path)
    gt_index = {n: i for i, n in enumerate(gt_names)}
    pairs = [
        (i, gt_index[n]) for i, n in enumerate(names)
        if n in gt_index and np.isfinite(T[i]).all() and np.isfinite(T_gt[gt_index[n]]).all()
    ]
    if len(pairs) < 3:
        raise InputError(
            f"only {len(pairs)} registered frames are shared with the ground truth {gt_poses_path} (need 3)",
            poses_path,
            "pass the poses.txt of the same sequence (frames are matched by name), or drop trajectory=",
        )
    ia, ib = (np.array(x) for x in zip(*pairs))
    A, B = T[ia], T_gt[ib]
    cams = camera_centers(torch.from_numpy(A)).numpy()
    gts = camera_centers(torch.from_numpy(B)).numpy()
    for c, path in ((cams, poses_path), (gts, gt_poses_path)):
        if not np.ptp(c, axis=0).max() > 1e-9 * max(1.0, np.abs(c).max()):
            raise InputError(f"the {len(c)} shared frames' camera centres all coincide: they give no scale", path,
                             "pass the poses of a moving camera, or drop trajectory= / gt_trajectory= (global "
                             "registration)")
    return cams, gts, A[:, :3, :3], B[:, :3, :3]


def run(cfg: DictConfig) -> Path:
    """Evaluate ``cfg.mesh`` against ``cfg.reference``; returns the output directory."""
    for key, what in (("mesh", "the reconstructed mesh (.ply)"), ("reference", "the reference (CT) surface in mm")):
        if OmegaConf.is_missing(cfg, key) or cfg.get(key) in (None, ""):
            raise InputError(f"{key}= is required: {what}", fix="python evaluate.py mesh=<ply> reference=<ply> "
                             "[trajectory=<poses.txt> gt_trajectory=<poses.txt>]")
    out = Path(str(cfg.out))
    traj = cfg.get("trajectory")
    gt_traj = cfg.get("gt_trajectory")
    if (traj is None) != (gt_traj is None):
        given = traj if traj is not None else gt_traj
        raise InputError(
            "only one of trajectory / gt_trajectory is given", given,
            "pass both (reconstruction poses.txt and ground-truth poses.txt) or neither",
        )
    init = str((cfg.get("registration") or {}).get("init", "auto"))
    if init not in INITS:  # before any mesh is read and sampled
        raise InputError(f"registration.init={init!r} is not one of {', '.join(INITS)}",
                         fix="pass registration.init=auto (trajectory when given, else global)")
    if init == "trajectory" and traj is None:
        raise InputError("registration.init=trajectory needs the camera trajectories",
                         fix="pass trajectory=<reconstruction poses.txt> gt_trajectory=<ground-truth poses.txt>, "
                             "or registration.init=auto")
    kw = {}
    if traj is not None:
        cams, gts, rots, gt_rots = load_trajectories(traj, gt_traj)
        kw = dict(cam_centers=cams, gt_cam_centers=gts, cam_rotations=rots, gt_cam_rotations=gt_rots)
    reg = OmegaConf.to_container(cfg.registration, resolve=True) if cfg.get("registration") is not None else {}
    render = cfg.get("render") or {}
    metrics = evaluate_mesh(
        cfg.mesh, cfg.reference, out, n_points=int(cfg.n_points), seed=int(cfg.seed), registration=reg,
        heatmap_views=int(render.get("views", 3)), vmax_mm=render.get("vmax_mm"),
        overwrite=bool(cfg.get("overwrite", False)), **kw,
    )
    print_metrics(metrics, out)
    return out


def print_metrics(metrics: dict, out: Path) -> None:
    """A rich table of the residuals and the similarity found."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"residuals of {Path(metrics['inputs']['mesh']['path']).name} vs reference")
    table.add_column("metric")
    table.add_column("value", justify="right")
    for key, label in [("mean_mm", "mean"), ("median_mm", "median"), ("p95_mm", "95th percentile"),
                       ("max_mm", "max"), ("rmse_mm", "RMSE")]:
        table.add_row(label, f"{metrics[key]:.3f} mm")
    table.add_row("fraction < 1 mm", f"{100 * metrics['frac_below_1mm']:.1f} %")
    table.add_row("points", str(metrics["n_points"]))
    if metrics.get("ct_covered_mm2") is not None:  # residuals only speak for the surface that was reconstructed
        table.add_row(f"reference covered (within {metrics['coverage_within_mm']:g} mm)",
                      f"{metrics['ct_covered_mm2'] / 100:.1f} of {metrics['ct_area_mm2'] / 100:.1f} cm² "
                      f"(mesh {metrics['area_mm2'] / 100:.1f} cm²)")
    rho = metrics.get("std_residual_spearman")
    if rho is not None:  # near 0 or negative: the mesh's std colours do not show where it is wrong
        table.add_row("std vs residual (Spearman, vertices)", f"{rho:+.3f}")
    reg = metrics["registration"]
    table.add_row("registration", f"{reg['init']}, scale {metrics['sim3']['scale']:.5g}, fitness {reg['fitness']:.3f}")
    Console().print(table)
    Console().print(f"written to {out}")
