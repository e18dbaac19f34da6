"""Generator throughput: voxels/s per core for the full birch model, and peak memory.

Writes the "generate" section of results/bench.json.  The public MATLAB
reference generator manages ~2.4e4 voxels/s on one core of this machine
under Octave (measured for the project); the goal here is >= 2e7.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from _bench_json import write_section

from pipeline.microstructure.model import _tile, generate_block
from pipeline.microstructure.volume import WoodVolume
from pipeline.params import build_params, make_grid

REFERENCE_VOXELS_PER_S = 2.4e4


def kernel_rate(preset: str, overrides: dict, block=(128, 128, 128), n_blocks=4, seed=1) -> dict:
    """Single-thread voxels/s of generate_block; cold includes the distortion tiles."""
    p = build_params(preset, overrides=overrides)
    g = make_grid((4000.0, 4000.0, 4000.0), 0.5, (0.0, 0.0, 0.0), p)
    generate_block(p, g, (0, 0, 0), (8, 8, 8), seed=seed)  # compile / load the kernels
    _tile.cache_clear()
    nvox = int(np.prod(block))
    cold = []
    warm = []
    for b in range(n_blocks):
        start = (2000 + 512 * b, 1000, 0)  # far apart: every block needs its own tiles
        t0 = time.perf_counter()
        generate_block(p, g, start, block, seed=seed)
        cold.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        generate_block(p, g, (start[0], start[1], block[2]), block, seed=seed)
        warm.append(time.perf_counter() - t0)
    return {
        "block": list(block),
        "voxels_per_s_cold": nvox / float(np.median(cold)),
        "voxels_per_s_warm": nvox / float(np.median(warm)),
    }


def store_rate(size_um=(256.0, 256.0, 256.0), chunks=(128, 128, 128)) -> dict:
    """End to end: generate every chunk of a Zarr volume with the local thread pool."""
    p = build_params("birch")
    g = make_grid(size_um, 0.5, (0.0, 0.0, 0.0), p)
    tmp = Path(tempfile.mkdtemp())
    try:
        vol = WoodVolume.create(tmp / "v.zarr", p, g, seed=2, chunks=chunks)
        t0 = time.perf_counter()
        vol.generate(scheduler="threads")
        dt = time.perf_counter() - t0
        size = sum(f.stat().st_size for f in (tmp / "v.zarr").rglob("*") if f.is_file())
    finally:
        shutil.rmtree(tmp)
    nvox = int(np.prod(g.shape))
    cores = os.cpu_count() or 1
    return {
        "shape": list(g.shape),
        "chunks": list(chunks),
        "threads": cores,
        "seconds": dt,
        "voxels_per_s": nvox / dt,
        "voxels_per_s_per_core": nvox / dt / cores,
        "bytes_on_disk_per_voxel": size / nvox,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/bench.json")
    args = ap.parse_args()
    res = {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "processor": platform.processor() or platform.machine()},
        "reference_voxels_per_s": REFERENCE_VOXELS_PER_S,
        "goal_voxels_per_s_per_core": 2e7,
        "kernel_single_thread": {
            "birch": kernel_rate("birch", {}),
            "birch_no_vessels_no_rays": kernel_rate("birch", {"vessels": False, "ray_cells": False}),
            "birch_laminate_0_-45_90_45_0": kernel_rate(
                "birch", {"laminate": (0, -45, 90, 45, 0), "ply_thickness_um": 64.0}),
            "balsa": kernel_rate("balsa", {}),
        },
        "zarr_store_all_cores": store_rate(),
    }
    birch = res["kernel_single_thread"]["birch"]["voxels_per_s_warm"]
    res["speedup_over_reference_per_core"] = birch / REFERENCE_VOXELS_PER_S
    res["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    write_section(args.out, "generate", res)


if __name__ == "__main__":
    main()
