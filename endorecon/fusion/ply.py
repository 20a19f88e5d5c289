"""PLY I/O for fused meshes with a per-vertex ``std``.

Open3D 0.20's ``t.io.write_triangle_mesh`` drops custom vertex attributes
(checked: an ``std`` vertex attribute is not written), so the mesh is written
here as binary little-endian PLY:

    vertex: float x y z, float nx ny nz (if present), uchar red green blue
            (if present), float std (if present)
    face:   list uchar int vertex_indices

Any PLY reader (Open3D, MeshLab, trimesh) reads the geometry and colours and
ignores ``std``; :func:`read_mesh_ply` reads it back too.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import open3d.core as o3c

from endorecon.utils.errors import InputError

__all__ = ["write_mesh_ply", "read_mesh_ply", "boundary_trim_rings_of", "ply_header_lines"]


TRIM_COMMENT = "comment boundary_trim_rings "


def write_mesh_ply(path: str | Path, mesh: o3d.t.geometry.TriangleMesh, boundary_trim_rings: int | None = None) -> Path:
    """Write ``mesh`` (positions, optional normals/colors [0, 1]/std (V, 1), triangles) to ``path``;
    ``boundary_trim_rings`` (if given) is recorded in the header (:func:`boundary_trim_rings_of`)."""
    path = Path(path)
    v = mesh.vertex
    pos = v.positions.cpu().numpy().astype(np.float32) if "positions" in v else np.zeros((0, 3), np.float32)
    n = len(pos)
    fields: list[tuple[str, str]] = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    cols = {"x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2]}
    if "normals" in v and n:
        nor = v.normals.cpu().numpy().astype(np.float32)
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
        cols.update(nx=nor[:, 0], ny=nor[:, 1], nz=nor[:, 2])
    if "colors" in v and n:
        c = np.clip(np.rint(v.colors.cpu().numpy().astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        cols.update(red=c[:, 0], green=c[:, 1], blue=c[:, 2])
    if "std" in v and n:
        fields.append(("std", "<f4"))
        cols["std"] = v["std"].cpu().numpy().reshape(n).astype(np.float32)
    vert = np.empty(n, dtype=np.dtype(fields))
    for name, _ in fields:
        vert[name] = cols[name]
    tri = mesh.triangle.indices.cpu().numpy().astype(np.int32) if "indices" in mesh.triangle else np.zeros((0, 3), np.int32)
    face = np.empty(len(tri), dtype=np.dtype([("n", "u1"), ("i", "<i4", (3,))]))
    face["n"] = 3
    face["i"] = tri
    ptype = {"<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0",
              "comment endorecon fused mesh" + ("; std = per-vertex depth std" if "std" in cols else "")]
    if boundary_trim_rings is not None:
        header.append(f"{TRIM_COMMENT}{int(boundary_trim_rings)}")
    header.append(f"element vertex {n}")
    header += [f"property {ptype[t]} {name}" for name, t in fields]
    header += [f"element face {len(tri)}", "property list uchar int vertex_indices", "end_header"]
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(vert.tobytes())
        f.write(face.tobytes())
    return path


def ply_header_lines(path: str | Path, max_bytes: int = 4096) -> list[str]:
    """The header lines of the PLY at ``path`` (before ``end_header``), reading only its first bytes."""
    with open(path, "rb") as f:
        head = f.read(max_bytes)
    return head.split(b"end_header")[0].decode("ascii", "replace").splitlines()


def boundary_trim_rings_of(path: str | Path) -> int:
    """Boundary rings trimmed off the mesh at ``path`` when it was saved (0 if its header does not say)."""
    for line in ply_header_lines(path):
        if line.startswith(TRIM_COMMENT):
            return int(line[len(TRIM_COMMENT):])
    return 0


def read_mesh_ply(path: str | Path) -> o3d.t.geometry.TriangleMesh:
    """Read a PLY written by :func:`write_mesh_ply` (std included) as an ``open3d.t`` mesh."""
    path = Path(path)
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise InputError("not a PLY file", path, fix="pass a mesh.ply written by endorecon's fusion")
    header = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise InputError("only binary little-endian PLY written by endorecon is supported here", path,
                         fix="read other PLY files with open3d.t.io.read_triangle_mesh")
    ptype = {"float": "<f4", "uchar": "u1"}
    fields, nv, nf, elem = [], 0, 0, None
    for line in header:
        tok = line.split()
        if tok[:2] == ["element", "vertex"]:
            nv, elem = int(tok[2]), "vertex"
        elif tok[:2] == ["element", "face"]:
            nf, elem = int(tok[2]), "face"
        elif tok[:1] == ["property"] and elem == "vertex":
            if tok[1] not in ptype:
                raise InputError(f"unsupported vertex property type {tok[1]}", path)
            fields.append((tok[2], ptype[tok[1]]))
    vdt = np.dtype(fields)
    off = end + len(b"end_header\n")
    need = off + nv * vdt.itemsize + nf * 13  # each face: a uchar count and three int32 indices
    if len(data) < need:
        raise InputError(f"PLY is truncated: {len(data)} bytes, its header announces {need} ({nv} vertices, "
                         f"{nf} faces)", path, fix="the file was cut (disk full, copy interrupted): make it again")
    vert = np.frombuffer(data, dtype=vdt, count=nv, offset=off)
    face = np.frombuffer(data, dtype=np.dtype([("n", "u1"), ("i", "<i4", (3,))]), count=nf, offset=off + nv * vdt.itemsize)
    mesh = o3d.t.geometry.TriangleMesh()
    names = vdt.names
    mesh.vertex.positions = o3c.Tensor(np.stack([vert["x"], vert["y"], vert["z"]], 1).astype(np.float32))
    if "nx" in names:
        mesh.vertex.normals = o3c.Tensor(np.stack([vert["nx"], vert["ny"], vert["nz"]], 1).astype(np.float32))
    if "red" in names:
        mesh.vertex.colors = o3c.Tensor(np.stack([vert["red"], vert["green"], vert["blue"]], 1).astype(np.float32) / 255.0)
    if "std" in names:
        mesh.vertex["std"] = o3c.Tensor(np.ascontiguousarray(vert["std"], dtype=np.float32)[:, None])
    mesh.triangle.indices = o3c.Tensor(np.ascontiguousarray(face["i"]).astype(np.int32))
    return mesh
