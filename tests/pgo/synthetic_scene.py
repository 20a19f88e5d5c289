"""A tiny analytic scene for the failure-detection and pose-graph tests.

The camera moves inside an ellipsoid (a closed, curved "cavity" seen from
inside, so every surface point in view is visible and depth is finite
everywhere).  Depth is ray-cast in closed form; sparse flow is the exact flow
of the true depth and poses, kept at a random few percent of the pixels.
Depths are ~1 (the SfM normalisation, median sparse depth ~1).
"""

from __future__ import annotations

import dataclasses

import torch

from endorecon.geometry import flow_from_depth, invert_pose, pixel_grid, pose_from_rt, relative_pose, so3_exp

D = torch.float64
SEMI_AXES = (1.0, 0.8, 1.7)  # ellipsoid centred at the world origin


@dataclasses.dataclass
class Scene:
    K: torch.Tensor  # (3, 3)
    cam_from_world: torch.Tensor  # (N, 4, 4)
    depth: torch.Tensor  # (N, 1, H, W)
    mask: torch.Tensor  # (1, H, W) bool
    flow_keep: torch.Tensor  # (N, 1, H, W) bool: pixels of each frame that carry a sparse track

    def render(self, cam_from_world: torch.Tensor) -> torch.Tensor:
        return render_depth(self.K, cam_from_world, self.depth.shape[-2], self.depth.shape[-1])

    def sparse_flow_fn(self, i: int, j: int, noise_px: float = 0.0, seed: int = 0):
        """Sparse flow i->j from the true depth and poses: (flow (2,H,W), valid (1,H,W))."""
        T = relative_pose(self.cam_from_world[i : i + 1], self.cam_from_world[j : j + 1])
        flow, z_j = flow_from_depth(self.depth[i : i + 1], self.K[None], T)
        H, W = self.depth.shape[-2:]
        uv = pixel_grid(H, W, dtype=D).permute(2, 0, 1)[None] + flow
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1)
        valid = self.flow_keep[i] & self.mask & inside & (z_j[:, 0] > 0)
        if noise_px > 0:
            g = torch.Generator().manual_seed(seed * 1000 + i * 37 + j)
            flow = flow + noise_px * torch.randn(flow.shape, generator=g, dtype=D)
        return torch.where(valid, flow[0], torch.zeros_like(flow[0])), valid


def render_depth(K: torch.Tensor, cam_from_world: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """z-depth of the ellipsoid's inside wall: K (3,3), cam_from_world (N,4,4) -> (N,1,H,W)."""
    a = torch.tensor(SEMI_AXES, dtype=D)
    uv = pixel_grid(H, W, dtype=D).reshape(-1, 2)
    rays = torch.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], torch.ones(len(uv), dtype=D)], 1)
    world_from_cam = invert_pose(cam_from_world)
    o = world_from_cam[:, None, :3, 3] / a  # (N, 1, 3)
    d = (rays @ world_from_cam[:, :3, :3].transpose(1, 2)) / a  # (N, HW, 3); z_cam of the ray is 1, so t is z-depth
    A = (d * d).sum(-1)
    B = 2 * (o * d).sum(-1)
    C = (o * o).sum(-1) - 1  # < 0: camera inside
    t = (-B + (B * B - 4 * A * C).sqrt()) / (2 * A)
    return t.view(-1, 1, H, W)


def make_scene(n_frames: int = 12, H: int = 64, W: int = 80, keep: float = 0.05, seed: int = 0) -> Scene:
    """Camera starts 0.3 inside the ellipsoid's centre and moves forward 0.03 a frame, turning ~0.7° a frame."""
    K = torch.tensor([[60.0, 0, (W - 1) / 2], [0, 60.0, (H - 1) / 2], [0, 0, 1]], dtype=D)
    k = torch.arange(n_frames, dtype=D)
    w = torch.stack([0.012 * k, 0.008 * torch.sin(0.5 * k), 0.01 * k], 1)  # world_from_cam rotation (axis-angle)
    R_wc = so3_exp(w)
    c = torch.stack([0.05 + 0.01 * k, -0.05 + 0.004 * k, 0.3 + 0.03 * k], 1)  # camera centres
    world_from_cam = pose_from_rt(R_wc, c)
    cam_from_world = invert_pose(world_from_cam)
    depth = render_depth(K, cam_from_world, H, W)
    uv = pixel_grid(H, W, dtype=D)
    r = ((uv[..., 0] - K[0, 2]) ** 2 + (uv[..., 1] - K[1, 2]) ** 2).sqrt()
    mask = (r < 0.55 * W)[None]
    g = torch.Generator().manual_seed(seed)
    flow_keep = torch.rand((n_frames, 1, H, W), generator=g, dtype=D) < keep
    return Scene(K=K, cam_from_world=cam_from_world, depth=depth, mask=mask, flow_keep=flow_keep)
