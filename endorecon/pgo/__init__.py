"""Dense pose graph optimisation of all frames' poses against the network's depth and the SfM tracks."""

from endorecon.pgo.optimize import PGOResult, optimize_poses, run

__all__ = ["PGOResult", "optimize_poses", "run"]
