"""Benchmark: the cost of the inference-time options against the network forward they follow.

``DepthModule.predict`` (network forward + frame scale) is timed without and with
``model.local_scaling``, and with local scaling and ``model.flip_average`` (a second
forward of the mirrored frames), on the same random frames and sparse points (~1 % of
the pixels, as the phantom's SfM gives), at 128x160 (CPU model) and 256x320
(FC-DenseNet-57), interleaved, best of N.  Prints ms per batch and the ratios to the first.

    .venv/bin/python benchmarks/local_scaling.py
    .venv/bin/python benchmarks/local_scaling.py --batch 8 --repeats 5
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hydra import compose, initialize_config_dir  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from endorecon.module import DepthModule  # noqa: E402

CONF = Path(__file__).resolve().parents[1] / "conf"


def _seconds(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    torch.manual_seed(0)
    for model, (H, W) in (("fcdensenet_cpu", (128, 160)), ("fcdensenet57", (256, 320))):
        with initialize_config_dir(config_dir=str(CONF), version_base=None):
            cfg = compose("train", overrides=[f"model={model}"])
        model_cfg = OmegaConf.to_container(cfg.model, resolve=True)
        model_cfg["local_scaling"]["enabled"] = True  # the configured sigma and prior, whether on by default or not
        module = DepthModule(model_cfg, cfg.loss).eval()
        ls = module.local_scaling
        B = args.batch
        img = torch.rand(B, 3, H, W)
        mask = torch.ones(B, 1, H, W, dtype=torch.bool)
        valid = torch.rand(B, 1, H, W) < 0.01
        sparse = torch.where(valid, torch.rand(B, 1, H, W) + 0.5, torch.zeros(()))
        variants = {"frame scale only": (None, False), "with local scaling": (ls, False),
                    "local scaling + flip averaging": (ls, True)}
        times = {name: [] for name in variants}
        with torch.no_grad():
            module.predict(img, mask, sparse, valid)  # warm-up (allocator, oneDNN kernels)
            for _ in range(args.repeats):  # interleaved: all see the same machine load
                for name, (local, flip) in variants.items():
                    module.local_scaling, module.flip_average = local, flip
                    times[name].append(_seconds(lambda: module.predict(img, mask, sparse, valid)))
        a, b, c = (min(times[name]) for name in variants)
        sigma = ls["sigma_fraction"] * W
        print(f"{model} {H}x{W}, batch {B}, sigma {sigma:.0f} px: predict {1e3 * a:.1f} ms, "
              f"with local scaling {1e3 * b:.1f} ms (ratio {b / a:.3f}), and flip averaging {1e3 * c:.1f} ms "
              f"(ratio {c / a:.3f}) (best of {args.repeats})")


if __name__ == "__main__":
    main()
