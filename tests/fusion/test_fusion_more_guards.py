"""More mutation guards for the fused-mesh PLY I/O and the mesh-level steps of fusion."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from endorecon.fusion import (
    AdaptiveTSDF,
    PlainTSDF,
    drop_small_components,
    drop_uncertain,
    read_mesh_ply,
    trim_boundary,
    write_mesh_ply,
)
from endorecon.fusion.tsdf import _torch_view
from endorecon.utils.errors import InputError

from test_fusion import H, K, W, _grid_mesh, integrate_all


def _mesh_with_everything(n: int = 5) -> o3d.t.geometry.TriangleMesh:
    m = _grid_mesh(n)
    V = n * n
    rng = np.random.default_rng(0)
    nrm = rng.normal(size=(V, 3)).astype(np.float32)
    m.vertex.normals = o3d.core.Tensor(nrm / np.linalg.norm(nrm, axis=1, keepdims=True))
    m.vertex.colors = o3d.core.Tensor(np.full((V, 3), 0.25, np.float32))
    m.vertex["std"] = o3d.core.Tensor(rng.uniform(0.001, 0.01, (V, 1)).astype(np.float32))
    return m


def test_ply_round_trip_keeps_normals_and_rounds_colours(tmp_path):
    m = _mesh_with_everything()
    back = read_mesh_ply(write_mesh_ply(tmp_path / "m.ply", m))
    assert np.array_equal(back.vertex.positions.numpy(), m.vertex.positions.numpy())
    assert "normals" in back.vertex
    assert np.array_equal(back.vertex.normals.numpy(), m.vertex.normals.numpy())
    # 0.25 * 255 = 63.75: rounded to 64, not cut to 63
    assert np.array_equal(back.vertex.colors.numpy(), np.full_like(back.vertex.colors.numpy(), 64 / 255))
    assert np.array_equal(back.vertex["std"].numpy(), m.vertex["std"].numpy())
    assert np.array_equal(back.triangle.indices.numpy(), m.triangle.indices.numpy())


def test_ply_missing_its_last_byte_is_truncated(tmp_path):
    path = write_mesh_ply(tmp_path / "m.ply", _mesh_with_everything())
    cut = tmp_path / "cut.ply"
    cut.write_bytes(path.read_bytes()[:-1])
    with pytest.raises(InputError, match="truncated") as e:
        read_mesh_ply(cut)
    assert e.value.path == cut


def test_trim_boundary_does_not_depend_on_vertex_numbering():
    """Every boundary vertex counts, whichever end of its boundary edges it is: a mid-edge boundary vertex
    renumbered 0 (the smaller end of both its boundary edges) still takes its triangles with it."""
    n = 6
    grid = _grid_mesh(n)
    pos = grid.vertex.positions.numpy()
    faces = grid.triangle.indices.numpy()
    for target in (3, 3 * n):  # vertices (0, 3) and (3, 0): mid-edge boundary vertices
        order = np.r_[target, np.delete(np.arange(n * n), target)]  # new vertex k is old vertex order[k]
        new_index = np.argsort(order)
        m = o3d.t.geometry.TriangleMesh()
        m.vertex.positions = o3d.core.Tensor(pos[order])
        m.triangle.indices = o3d.core.Tensor(new_index[faces])
        out = trim_boundary(m, 1)
        assert len(out.triangle.indices) == 2 * (n - 3) ** 2
        assert out.vertex.positions.numpy()[:, :2].min() == 1


def test_piece_of_exactly_min_fraction_is_kept():
    """Pieces with fewer than min_fraction of the triangles go; one with exactly that share stays."""
    a = _grid_mesh(3)  # 8 triangles
    b = _grid_mesh(5)  # 32 triangles: a has 8 / 40 = 20 %
    pa = a.vertex.positions.numpy()
    pb = b.vertex.positions.numpy() + np.array([10, 0, 0], np.float32)
    m = o3d.t.geometry.TriangleMesh()
    m.vertex.positions = o3d.core.Tensor(np.concatenate([pa, pb]))
    m.triangle.indices = o3d.core.Tensor(np.concatenate([a.triangle.indices.numpy(), b.triangle.indices.numpy() + len(pa)]))
    assert len(drop_small_components(m, 0.2).triangle.indices) == 40
    assert len(drop_small_components(m, 0.21).triangle.indices) == 32


def test_pieces_joined_only_through_a_triangles_last_edge_are_one_piece():
    """Connectivity uses all three edges: two triangles that share only the edge (2, 0) of one of them are one piece."""
    m = o3d.t.geometry.TriangleMesh()
    m.vertex.positions = o3d.core.Tensor(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 1, 0], [5, 5, 5], [6, 5, 5],
                                                   [5, 6, 5]], np.float32))
    # the pair shares vertices 0 and 2 only through edges (2, 0) of the first and (0, 3), (3, 2) of the second
    m.triangle.indices = o3d.core.Tensor(np.array([[1, 2, 0], [0, 3, 2], [4, 5, 6]], np.int64))
    out = drop_small_components(m, 0.5)  # the pair has 2 / 3 of the triangles: kept whole
    assert len(out.triangle.indices) == 2


def test_drop_uncertain_median_is_over_the_used_vertices_only():
    """Vertices no triangle uses (however large their std) have no say in the median."""
    n = 6
    grid = _grid_mesh(n)
    pos = grid.vertex.positions.numpy()
    m = o3d.t.geometry.TriangleMesh()
    m.vertex.positions = o3d.core.Tensor(np.concatenate([pos, pos + 100, pos + 200]))  # 72 unused vertices
    m.triangle.indices = grid.triangle.indices
    std = np.ones((3 * n * n, 1), np.float32)
    std[2 * n + 3] = 3.0  # an interior vertex: six triangles
    std[n * n:] = 10.0
    m.vertex["std"] = o3d.core.Tensor(std)
    out, info = drop_uncertain(m, 2.0)
    assert info["median_std"] == 1.0 and info["removed"] == 6
    assert len(out.triangle.indices) == len(grid.triangle.indices) - 6


def test_saved_mesh_drops_pieces_that_the_trim_leaves_under_min_component_fraction(tmp_path):
    """A small piece holds 10 % of the extracted triangles (kept at min_component_fraction = 0.05); one ring of
    trim leaves it 2 of 100: the saved mesh must not keep it."""
    big, small = _grid_mesh(10), _grid_mesh(4)  # 162 and 18 triangles
    pb = big.vertex.positions.numpy()
    ps = small.vertex.positions.numpy() + np.array([50, 0, 0], np.float32)
    m = o3d.t.geometry.TriangleMesh()
    m.vertex.positions = o3d.core.Tensor(np.concatenate([pb, ps]))
    m.triangle.indices = o3d.core.Tensor(np.concatenate([big.triangle.indices.numpy(),
                                                         small.triangle.indices.numpy() + len(pb)]))
    assert len(drop_small_components(m, 0.05).triangle.indices) == 180  # extraction keeps it
    vol = PlainTSDF(0.02, min_component_fraction=0.05, boundary_trim_rings=1)
    vol.extract_mesh = lambda: m
    saved = read_mesh_ply(vol.save_mesh(tmp_path / "mesh.ply"))
    assert len(saved.triangle.indices) == 2 * 7 ** 2
    assert saved.vertex.positions.numpy()[:, 0].max() < 50


def test_plain_tsdf_band_is_trunc_voxels_wide():
    """PlainTSDF fuses trunc_voxels voxels each side of the surface (not fewer)."""
    voxel, trunc = 0.01, 6.0
    vol = PlainTSDF(voxel, trunc_voxels=trunc, block_search="every_pixel")
    vol.integrate(np.full((H, W), 1.0, np.float32), None, None, K, np.eye(4))
    coords, idx = vol.vbg.voxel_coordinates_and_flattened_indices()
    w = _torch_view(vol.vbg.attribute("weight")).reshape(-1).cpu().numpy()[idx.cpu().numpy()]
    z = coords.cpu().numpy()[:, 2][w > 0]
    reach = (z - 1.0).max() / voxel  # behind the surface (in front, the whole touched block is free space)
    assert 0.8 * trunc <= reach <= 1.2 * trunc, reach



@pytest.mark.parametrize("cls", [AdaptiveTSDF, PlainTSDF])
def test_each_vertex_takes_the_colour_of_the_pixel_it_projects_to(cls):
    """A frontal plane with a random colour per pixel: the fused mesh's vertices show the colour of the pixel
    nearest their projection through the pixel-centre K.  A principal point off by the corner convention's half
    pixel, or by the plain TSDF's one-pixel padding, shows a neighbour's colour at half or all of them."""
    z, voxel = 1.0013, 0.004  # one pixel at z = 1: 1 / 70 = 3.6 voxels; z off the voxel grid's layers
    colour = np.random.default_rng(0).random((H, W, 3)).astype(np.float32)
    vol = cls(voxel, **({"compile": False} if cls is AdaptiveTSDF else {}))
    integrate_all(vol, [np.full((H, W), z)], [np.full((H, W), voxel)], [np.eye(4)], [colour])
    mesh = vol.extract_mesh()
    p, c = mesh.vertex.positions.numpy().astype(float), mesh.vertex.colors.numpy()
    assert len(p) > 10000
    u = np.round(K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2]).astype(int)
    v = np.round(K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]).astype(int)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    assert inside.mean() > 0.99
    same = np.abs(colour[v[inside], u[inside]] - c[inside]).max(1) < 0.01
    # the rest: vertices between two voxels that see neighbouring pixels (a blend of the two)
    assert same.mean() > 0.8, same.mean()
