"""Shared test set-up."""

import os

# Idle OpenMP threads of torch and open3d spin and starve each other on 2 cores.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
