"""endorecon: self-supervised dense 3D reconstruction from monocular endoscopic video.

Conventions (poses, pixels, depth, units) are documented once in
:mod:`endorecon.geometry`.
"""

__version__ = "0.1.0"
