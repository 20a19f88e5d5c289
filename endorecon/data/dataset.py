"""Read a phantom dataset (``python -m endorecon.phantom``): sequences, and ground truth kept apart.

:func:`load_dataset` returns what the pipeline may see (frames, mask,
intrinsics).  :func:`load_ground_truth` and :func:`patients_with_ct` are the
only way to open the ground truth; evaluation and tests call them, training
code never does.  The layout is documented in :mod:`endorecon.phantom.generate`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from endorecon.data.sequence import GroundTruth, Sequence, load_sequence_folder, read_poses_txt
from endorecon.utils.errors import InputError
from endorecon.utils.io import read_json

FORMAT = "endorecon-phantom"

__all__ = ["load_dataset", "load_ground_truth", "patients_with_ct", "read_dataset_meta"]


def read_dataset_meta(root: str | Path) -> dict:
    """``dataset.json`` of a complete phantom dataset; a clear error if missing or incomplete."""
    root = Path(root)
    if not root.is_dir():
        raise InputError("phantom dataset folder does not exist", root, "generate it: python -m endorecon.phantom out=<dir>")
    if not (root / "COMPLETE").is_file():
        raise InputError(
            "phantom dataset is incomplete (no COMPLETE marker)", root, "delete the folder and generate it again"
        )
    meta = read_json(root / "dataset.json", "generate the dataset again")
    if meta.get("format") != FORMAT or "patients" not in meta:
        raise InputError(f"not an {FORMAT} dataset", root / "dataset.json", "point at a folder made by endorecon.phantom")
    if meta.get("version", 0) > 1:
        raise InputError(f"dataset version {meta.get('version')} is newer than this code reads (1)", root)
    return meta


def load_dataset(root: str | Path) -> list[Sequence]:
    """All sequences of a phantom dataset, ordered by patient then sequence.

    Each :class:`Sequence` has ``name`` "patient_00/seq_00", ``patient`` set, ``units`` "mm",
    ``source`` "phantom" and no poses (the pipeline estimates them).
    """
    root = Path(root)
    meta = read_dataset_meta(root)
    seqs = []
    for p in meta["patients"]:
        pid = int(p["id"])
        for s in p["sequences"]:
            name = f"patient_{pid:02d}/{s}"
            seq = load_sequence_folder(root / name, name=name, patient=pid)
            seqs.append(seq.replace(name=name, patient=pid, source="phantom"))
    return seqs


def patients_with_ct(root: str | Path) -> list[int]:
    """Ids of the patients whose CT (mesh) evaluation may use."""
    return [int(p["id"]) for p in read_dataset_meta(root)["patients"] if p.get("has_ct")]


def load_ground_truth(root: str | Path, patient: int, seq: str = "seq_00") -> GroundTruth:
    """Ground truth of one sequence: depth (N, H, W) mm, cam_from_world (N, 4, 4) mm, CT mesh path.

    ``mesh_path`` is None for train-only patients (``has_ct`` false), as evaluation must not use it.
    """
    root = Path(root)
    meta = read_dataset_meta(root)
    entry = next((p for p in meta["patients"] if int(p["id"]) == int(patient)), None)
    if entry is None:
        raise InputError(f"no patient {patient} in the dataset", root / "dataset.json", "pick one of its patient ids")
    if seq not in entry["sequences"]:
        raise InputError(f"patient {patient} has no sequence {seq!r} (has {entry['sequences']})", root / "dataset.json")
    gt_dir = root / "ground_truth" / f"patient_{int(patient):02d}" / seq
    depth_path = gt_dir / "depth_mm.npz"
    if not depth_path.is_file():
        raise InputError("ground-truth depth is missing", depth_path, "generate the dataset again")
    try:
        with np.load(depth_path, allow_pickle=False) as z:
            depth = z["depth_mm"].astype(np.float32)
    except (KeyError, ValueError, OSError) as e:
        raise InputError(f"cannot read ground-truth depth ({e})", depth_path, "generate the dataset again") from e
    _, poses = read_poses_txt(gt_dir / "poses.txt")
    if len(poses) != len(depth):
        raise InputError(f"{len(poses)} poses but {len(depth)} depth maps", gt_dir, "generate the dataset again")
    mesh = root / "ground_truth" / f"patient_{int(patient):02d}" / "mesh.ply"
    if entry.get("has_ct") and not mesh.is_file():
        raise InputError("CT mesh is missing", mesh, "generate the dataset again")
    return GroundTruth(depth_mm=depth, cam_from_world=poses, mesh_path=mesh if entry.get("has_ct") else None)
