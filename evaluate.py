"""Evaluate a mesh against a reference surface: ``python evaluate.py mesh=<ply> reference=<ply>``."""

import os

# Idle OpenMP threads of torch and open3d spin and starve each other (~10x slower fusion on 2 cores).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

import endorecon.utils.resolvers  # noqa: E402,F401  (config resolvers)


@hydra.main(config_path="conf", config_name="evaluate", version_base="1.3")
def main(cfg: DictConfig):
    from endorecon.tasks.evaluate import run
    from endorecon.utils.cli import report_errors

    return report_errors(run, cfg)


if __name__ == "__main__":
    main()
