"""Train the depth network with bootstrapping: ``python train.py fold=3 iteration=2``."""

import sys

import hydra
from omegaconf import DictConfig

import endorecon.utils.resolvers  # noqa: F401  (config resolvers)


# Path overrides are quoted for Hydra, so any path works (e.g. a checkpoint under .../fold=0/...).
PATH_KEYS = ("ckpt_path",)


@hydra.main(config_path="conf", config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> float | None:
    from endorecon.tasks.train import run
    from endorecon.utils.cli import report_errors

    return report_errors(run, cfg)


if __name__ == "__main__":
    from endorecon.utils.cli import quote_path_overrides

    sys.argv = sys.argv[:1] + quote_path_overrides(sys.argv[1:], PATH_KEYS)
    main()
