"""Evaluate a mesh against a reference surface: ``python evaluate.py mesh=<ply> reference=<ply>``."""

import sys

import hydra
from omegaconf import DictConfig

import endorecon.utils.resolvers  # noqa: F401  (config resolvers)


# Path overrides are quoted for Hydra, so any path works (e.g. a mesh under .../fold=0/iteration=1/).
PATH_KEYS = ("mesh", "reference", "trajectory", "gt_trajectory", "out")


@hydra.main(config_path="conf", config_name="evaluate", version_base="1.3")
def main(cfg: DictConfig):
    from endorecon.tasks.evaluate import run
    from endorecon.utils.cli import report_errors

    return report_errors(run, cfg)


if __name__ == "__main__":
    from endorecon.utils.cli import quote_path_overrides

    sys.argv = sys.argv[:1] + quote_path_overrides(sys.argv[1:], PATH_KEYS)
    main()
