"""Phantom rendering speed at 256x320: geometry pass (ray cast + normals) and full shaded frames.

``python benchmarks/phantom_render.py [--frames 60] [--threads 2]`` prints frames/s and each pass's ratio
against the batched depth-only ray cast of the same run (the peer).
Target (issue 4): geometry pass >= 50 frames/s on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from endorecon.phantom.anatomy import make_anatomy
from endorecon.phantom.appearance import SolidTexture
from endorecon.phantom.generate import render_video
from endorecon.phantom.trajectory import endoscope_camera, plan_trajectory
from endorecon.rendering import MeshRenderer, render_depth


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--threads", type=int, default=0, help="Open3D ray-casting threads (0 = all)")
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    h, w, n = a.height, a.width, a.frames
    anat = make_anatomy(0)
    t0 = time.perf_counter()
    r = MeshRenderer((anat.vertices, anat.triangles), n_threads=a.threads)
    K, mask = endoscope_camera(h, w)
    T = plan_trajectory(anat.centreline, anat.clearance, n, np.random.default_rng(0))
    r.render(K, T[0], h, w)  # builds the BVH
    print(f"mesh {len(anat.triangles)} triangles; scene build + first cast {time.perf_counter() - t0:.3f} s")

    def best(fn):
        """Best wall time of the repeats, and the process CPU time (all threads) of that repeat."""
        runs = []
        for _ in range(a.repeats):
            t, c = time.perf_counter(), time.process_time()
            fn()
            runs.append((time.perf_counter() - t, time.process_time() - c))
        return min(runs)

    rates = {}

    def report(what, frames, wall_cpu):
        wall, cpu = wall_cpu
        rates[what] = frames / wall
        peer = next(iter(rates.values()))
        # on a shared machine wall time depends on the load; CPU seconds per frame do not
        print(f"{what:58s} {frames / wall:7.1f} frames/s wall (x{frames / wall / peer:.2f} of depth only), "
              f"{1000 * cpu / frames:6.1f} CPU-ms/frame")

    report("depth only (render_depth, batched)", n, best(lambda: render_depth(r, K, T, h, w, mask=mask)))
    report("geometry pass (render: depth, ids, uvs, normals, points)", n, best(lambda: [r.render(K, T[i], h, w) for i in range(n)]))
    tex = SolidTexture(0)
    m = min(n, 20)
    report("full shaded frame (geometry, texture, shading, sensor)", m, best(lambda: render_video(r, tex, K, mask, T[:m], np.random.default_rng(0))))


if __name__ == "__main__":
    main()
