"""The endoscopy phantom: procedural patients with exact ground truth.

Six (by default) deterministic nasal-cavity-like anatomies in millimetres,
each a watertight mesh (the patient's "CT"), with hand-held-like endoscope
videos rendered by ray casting (:mod:`endorecon.rendering`) and shaded like
endoscopy (point light at the camera, wet specular mucosa, vessels, noise,
JPEG).  Ground truth (z-depth in mm, poses, mesh) is written apart from what
the pipeline reads; read it only through :mod:`endorecon.data.dataset`.

Usage::

    python -m endorecon.phantom out=/tmp/ph patients=1 frames=40
    python -m endorecon.phantom out=/tmp/asr patients=1 mesh=../shared/data/nasal_cavity_mesh/ASR.ply
"""

from endorecon.phantom.generate import FORMAT, VERSION, ensure_dataset, generate, render_video

__all__ = ["generate", "ensure_dataset", "render_video", "FORMAT", "VERSION"]
