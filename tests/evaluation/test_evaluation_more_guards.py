"""More mutation guards for endorecon.evaluation.meshes.load_mesh: bad meshes are InputErrors naming the file."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from endorecon.evaluation import load_mesh
from endorecon.utils.errors import InputError


def _write(v, tri, path):
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(v, float)),
                                     o3d.utility.Vector3iVector(np.asarray(tri, np.int32)))
    assert o3d.io.write_triangle_mesh(str(path), mesh)
    return path


GOOD_V = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]
GOOD_T = [[0, 1, 2], [1, 3, 2]]


@pytest.mark.parametrize("case,match", [
    ("nan", "non-finite"),
    ("degenerate", "zero surface area"),
])
def test_load_mesh_refuses_meshes_that_cannot_be_evaluated(case, match, tmp_path):
    load_mesh(_write(GOOD_V, GOOD_T, tmp_path / "good.ply"))  # the healthy mesh loads
    v, t = [list(p) for p in GOOD_V], GOOD_T
    if case == "nan":
        v[3] = [np.nan, 1, 0]
    else:  # every triangle on a line
        v = [[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]]
    bad = _write(v, t, tmp_path / f"bad_{case}.ply")
    with pytest.raises(InputError, match=match) as e:
        load_mesh(bad)
    assert e.value.path == bad and bad.name in str(e.value)

