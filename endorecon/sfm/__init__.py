"""SfM stage: pycolmap with known intrinsics and the endoscope mask, automatic reruns, sparse-cloud cleaning.

``endorecon.sfm.colmap`` is the only module of endorecon that imports pycolmap.
Public API (imported lazily so that ``import endorecon.sfm`` stays cheap)::

    run(cfg_sfm, seq, out_dir) -> Path         # stage.run: writes model/, sequence.npz, attempts.json
    load_result(out_dir) -> Sequence
    rerun(cfg_sfm, seq, segment, attempt, out_dir) -> Sequence
    read_colmap_model(model_dir, frames) -> Sequence
    write_colmap_model(seq, out_dir, binary=True) -> Path
    SfMError
"""

_EXPORTS = {
    "run": "endorecon.sfm.stage",
    "load_result": "endorecon.sfm.stage",
    "rerun": "endorecon.sfm.stage",
    "SfMError": "endorecon.sfm.stage",
    "read_colmap_model": "endorecon.sfm.colmap",
    "write_colmap_model": "endorecon.sfm.colmap",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'endorecon.sfm' has no attribute {name!r}")
