"""Reconstruct a new video with a trained model: ``python reconstruct.py input=<video or frames> ckpt=<ckpt>``."""

import os
import re
import sys

# Idle OpenMP threads of torch and open3d spin and starve each other (~10x slower fusion on 2 cores).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

import endorecon.utils.resolvers  # noqa: E402,F401  (config resolvers)

PATH_KEYS = ("input", "ckpt", "intrinsics", "mask")


def quote_path_overrides(argv: list[str]) -> list[str]:
    """Quote the values of path overrides so that Hydra's grammar accepts any path, e.g. a checkpoint under
    ``outputs/train/fold=0/iteration=1/`` (an unquoted ``=`` is a Hydra syntax error)."""
    out = []
    for arg in argv:
        m = re.fullmatch(rf"(\+{{0,2}}(?:{'|'.join(PATH_KEYS)}))=(.*)", arg, flags=re.S)
        if m and m.group(2) and m.group(2)[0] not in "'\"" and m.group(2) != "null":
            val = m.group(2).replace("\\", "\\\\").replace("'", "\\'")
            arg = f"{m.group(1)}='{val}'"
        out.append(arg)
    return out


@hydra.main(config_path="conf", config_name="reconstruct", version_base="1.3")
def main(cfg: DictConfig):
    from endorecon.tasks.reconstruct import run
    from endorecon.utils.cli import report_errors

    return report_errors(run, cfg)


if __name__ == "__main__":
    sys.argv = sys.argv[:1] + quote_path_overrides(sys.argv[1:])
    main()
