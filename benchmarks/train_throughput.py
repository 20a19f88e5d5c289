"""Training throughput of the depth network at 128x160 on this machine, and the cost of the losses.

Two steps are timed alternately (interleaved, after warm-up steps, medians reported):

* ``full``: the DepthModule's training computation: network on both frames of B pairs,
  Depth Scaling Layer, the four NLL losses in both directions (dense simulation active),
  backward, optimizer step;
* ``net``: the same network forward + backward (loss = mean of the outputs) + optimizer step.

The difference is the cost of the scaling layer and the four losses (with their warps).
A third step, interleaved with them, is ``full`` with the network's memory layout flipped
(``net.channels_last``; same weights): the layout's speed-up, measured in the same run.

    .venv/bin/python benchmarks/train_throughput.py                       # default CPU model
    .venv/bin/python benchmarks/train_throughput.py --model conf/model/fcdensenet57.yaml
    .venv/bin/python benchmarks/train_throughput.py --set net.growth_rate=8 --set net.down_layers=[2,2,2,2,2]
    python benchmarks/train_throughput.py --device cuda --precision bf16 --height 256 --width 320   # a GPU

``--precision bf16`` / ``16`` runs forward and losses under autocast as Lightning's ``bf16-mixed`` /
``16-mixed`` do (``16`` with a gradient scaler); it also prints how far the mixed-precision losses of
the first batch are from the float32 ones.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import sys
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from endorecon.geometry import flow_from_depth, invert_pose  # noqa: E402
from endorecon.module import DepthModule  # noqa: E402
from endorecon.networks import count_parameters  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def synthetic_batch(B: int, H: int, W: int, seed: int = 0) -> dict:
    """Random texture, a fronto-parallel plane at depth 5, camera j moved sideways; 2 % sparse points."""
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[0.8 * W, 0.0, (W - 1) / 2], [0.0, 0.8 * W, (H - 1) / 2], [0.0, 0.0, 1.0]]).expand(B, 3, 3)
    T = torch.eye(4).repeat(B, 1, 1)
    T[:, 0, 3] = 0.3
    depth = torch.full((B, 1, H, W), 5.0)
    mask = torch.ones(B, 1, H, W, dtype=torch.bool)

    def pts():
        return torch.rand(B, 1, H, W, generator=g) < 0.02

    vi, vj, si = pts(), pts(), torch.zeros(B, 1, H, W, dtype=torch.bool)
    si[..., H // 4 : -H // 4, W // 4 : -W // 4] = True
    return {
        "image_i": torch.rand(B, 3, H, W, generator=g), "image_j": torch.rand(B, 3, H, W, generator=g),
        "mask_i": mask, "mask_j": mask.clone(), "K": K.clone(), "cam_j_from_cam_i": T,
        "sparse_depth_i": depth * vi, "sparse_depth_j": depth * vj, "sparse_valid_i": vi, "sparse_valid_j": vj,
        "sparse_flow_ij": flow_from_depth(depth, K, T)[0] * vi, "sparse_flow_valid_ij": vi,
        "sparse_flow_ji": flow_from_depth(depth, K, invert_pose(T))[0] * vj, "sparse_flow_valid_ji": vj,
        "sim_depth_i": depth.clone(), "sim_depth_j": depth.clone(), "sim_valid_i": si, "sim_valid_j": si.clone(),
        "index_i": torch.arange(B), "index_j": torch.arange(B) + 1, "has_sim": torch.ones(B, dtype=torch.bool),
    }  # fmt: skip


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default=str(ROOT / "conf/model/fcdensenet_cpu.yaml"))
    ap.add_argument("--loss", default=str(ROOT / "conf/loss/nll.yaml"))
    ap.add_argument("--set", action="append", default=[], help="dotted override of the model config, e.g. net.growth_rate=8")
    ap.add_argument("--pairs", type=int, default=4, help="pairs per batch (images per step = 2x)")
    ap.add_argument("--height", type=int, default=128)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--warmup", type=int, default=10)
    ap.add_argument("--iters", type=int, default=10)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0 = torch default)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda")
    ap.add_argument("--precision", default="32", choices=["32", "bf16", "16"], help="float32, or mixed precision")
    args = ap.parse_args(argv)
    dev = torch.device(args.device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: torch sees no CUDA device on this machine")
    if args.precision == "32":
        autocast = contextlib.nullcontext
    else:
        dtype = torch.bfloat16 if args.precision == "bf16" else torch.float16
        autocast = lambda: torch.autocast(dev.type, dtype=dtype)  # noqa: E731
    scaler = torch.amp.GradScaler(dev.type, enabled=args.precision == "16")

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize()
    if args.threads:
        torch.set_num_threads(args.threads)
    model_cfg = OmegaConf.merge(OmegaConf.load(args.model), OmegaConf.from_dotlist(args.set))
    torch.manual_seed(0)
    module = DepthModule(model_cfg, OmegaConf.load(args.loss)).to(dev)
    module.train()
    net = module.net
    opt = torch.optim.AdamW(module.parameters(), lr=1e-5)
    flipped_cfg = OmegaConf.merge(model_cfg, {"net": {"channels_last": not net.channels_last}})
    flipped = DepthModule(flipped_cfg, OmegaConf.load(args.loss)).to(dev)
    flipped.load_state_dict(module.state_dict())
    flipped.train()
    opt_flipped = torch.optim.AdamW(flipped.parameters(), lr=1e-5)
    batch = {k: v.to(dev) for k, v in synthetic_batch(args.pairs, args.height, args.width).items()}
    images = torch.cat([batch["image_i"], batch["image_j"]])
    masks = torch.cat([batch["mask_i"], batch["mask_j"]])

    if args.precision != "32":  # the mixed-precision losses against float32 ones, same weights and batch
        with torch.no_grad():
            ref = module.compute_losses(batch)
            with autocast():
                mixed = module.compute_losses(batch)
        print("losses float32 vs " + args.precision + "-mixed: " + ", ".join(
            f"{k} {ref[k].item():.4g} vs {mixed[k].item():.4g}" for k in ("sparse_depth", "depth_consistency",
                                                                         "sparse_flow", "dense_simulation")))

    def step(loss, opt):
        scaler.scale(loss).backward()
        scaler.step(opt)
        scaler.update()
        opt.zero_grad(set_to_none=True)

    def full(module=module, opt=opt):
        with autocast():
            parts = module.compute_losses(batch)
            total, _ = module.total_loss(parts, warmup=False)
        step(total, opt)
        return total

    def net_only():
        with autocast():
            d, s = net(images, masks)
            loss = d.mean() + s.mean()
        step(loss, opt)

    t_full, t_net, t_flip = [], [], []
    for k in range(args.warmup + args.iters):
        sync()
        t0 = time.perf_counter()
        total = full()
        sync()
        t1 = time.perf_counter()
        net_only()
        sync()
        t2 = time.perf_counter()
        full(flipped, opt_flipped)
        sync()
        t3 = time.perf_counter()
        if not torch.isfinite(total):
            raise RuntimeError(f"non-finite loss at step {k}")
        if k >= args.warmup:
            t_full.append(t1 - t0)
            t_net.append(t2 - t1)
            t_flip.append(t3 - t2)
    n_img = 2 * args.pairs
    mf, mn = statistics.median(t_full), statistics.median(t_net)
    print(f"model {args.model} {' '.join(args.set)}")
    where = torch.cuda.get_device_name(dev) if dev.type == "cuda" else f"cpu, torch threads {torch.get_num_threads()}"
    print(f"parameters {count_parameters(net):,}; {args.height}x{args.width}; {args.pairs} pairs = {n_img} images/step; "
          f"{where}; precision {args.precision}; load avg {os.getloadavg()[0]:.1f}")
    print(f"full training step  : median {mf:.3f} s  -> {n_img / mf:.2f} images/s  (min {min(t_full):.3f} s)")
    print(f"network fwd+bwd+step: median {mn:.3f} s  -> {n_img / mn:.2f} images/s  (min {min(t_net):.3f} s)")
    rel = [(f - n) / n for f, n in zip(t_full, t_net)]
    print(f"scaling + four losses cost {100 * (mf - mn) / mn:+.1f} % of the network step "
          f"(median of interleaved per-step ratios {100 * statistics.median(rel):+.1f} %)")
    mx = statistics.median(t_flip)
    layout = ("channels_last", "contiguous") if net.channels_last else ("contiguous", "channels_last")
    print(f"full training step with the network {layout[1]}: median {mx:.3f} s -> {n_img / mx:.2f} images/s; "
          f"{layout[0]} is x{mx / mf:.2f} that speed")


if __name__ == "__main__":
    main()
