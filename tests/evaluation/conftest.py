"""Small meshes for the evaluation tests: a decimated copy of the shared CT nasal-cavity mesh (mm)."""

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from endorecon.evaluation import Sim3

ASR = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "nasal_cavity_mesh" / "ASR.ply"


@pytest.fixture(scope="session")
def ct_mesh() -> o3d.geometry.TriangleMesh:
    """~2000-triangle nasal cavity in mm (or a torus when the shared data is absent)."""
    if ASR.is_file():
        mesh = o3d.io.read_triangle_mesh(str(ASR)).simplify_quadric_decimation(2000)
    else:  # keeps the tests runnable without ../shared
        mesh = o3d.geometry.TriangleMesh.create_torus(20.0, 6.0, 40, 16)
        v = np.asarray(mesh.vertices) * [1.0, 0.6, 1.3]
        # A squashed torus alone is symmetric under 180-degree turns about each axis, so a registration
        # could land on a turned copy: two unequal bumps on the ring leave it no symmetry.
        for angle, height in ((0.0, 6.0), (100.0, 3.0)):
            c = 20.0 * np.array([np.cos(np.radians(angle)), 0.6 * np.sin(np.radians(angle))])
            v[:, 2] += height * np.exp(-((v[:, :2] - c) ** 2).sum(1) / (2 * 5.0 ** 2))
        mesh.vertices = o3d.utility.Vector3dVector(v)
    mesh.remove_unreferenced_vertices()
    return mesh


@pytest.fixture(scope="session")
def ct_path(ct_mesh, tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("ct") / "ct.ply"
    o3d.io.write_triangle_mesh(str(p), ct_mesh)
    return p


@pytest.fixture(scope="session")
def recon_from_ct() -> Sim3:
    """A known similarity: the reconstruction's (arbitrary) frame from the CT frame."""
    R = Rotation.from_euler("xyz", [35.0, -50.0, 110.0], degrees=True).as_matrix()
    return Sim3(0.37, R, np.array([4.0, -3.0, 12.0]))


@pytest.fixture(scope="session")
def helpers():
    """Plain helper functions (tests import nothing from conftest)."""
    return type("Helpers", (), {"moved_mesh": staticmethod(_moved_mesh), "sim3_errors": staticmethod(_sim3_errors)})


def _moved_mesh(mesh: o3d.geometry.TriangleMesh, T: Sim3) -> o3d.geometry.TriangleMesh:
    out = o3d.geometry.TriangleMesh(mesh)
    out.vertices = o3d.utility.Vector3dVector(T.apply(np.asarray(mesh.vertices, dtype=np.float64)))
    return out


def _sim3_errors(A: Sim3, B: Sim3, extent: float) -> dict:
    """Relative errors of A vs B: scale, rotation (Frobenius), translation / extent."""
    return {
        "scale": abs(A.scale / B.scale - 1),
        "R": float(np.linalg.norm(A.R - B.R)),
        "t": float(np.linalg.norm(A.t - B.t)) / extent,
    }
