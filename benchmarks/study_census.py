"""Where a study's `exact` time goes on its workers: distortion tiles (how many, how often one is
built again on the same worker), regions, and the march, measured inside the workers.

Starts a local cluster of 2 single-threaded workers, wraps (on each worker, with ``client.run``)
the distortion tile kernel, the region builder and the march with counters, runs ``twray study``
against that cluster in a fresh cache, and reads the counters back:

    python benchmarks/study_census.py studies/table1/study-1.yaml --scale paper   (make bench-census)

Writes the "study_census" section of results/bench.json: per worker, the distortion tiles built,
how many of them were built before on that worker (and how many other woods had tiles built in
between), the stretches of woods, and the seconds in tiles, in regions (tiles included) and in
the march; the command's wall time (kernels compiled beforehand by the caller).

The counters are plain Python wrappers around whole kernel calls: they add microseconds to calls
of milliseconds and change no number.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _bench_json import write_section


def _install(tile_budget=None):
    """On a worker: wrap the tile kernel, the region builder and the march with counters (and set
    the tiles a worker keeps beside the wood in use, when ``tile_budget`` is given)."""
    import collections
    import time as _t

    from pipeline.microstructure import model, region
    from pipeline.optics import wood_surface

    if tile_budget is not None:
        model._TILES.budget = tile_budget

    state = {"tiles": collections.Counter(), "first": {}, "order": [], "woods_between": collections.Counter(),
             "tile_s": 0.0, "regions": 0, "region_s": 0.0,
             "march_s": 0.0, "marches": 0, "warm_s": 0.0}

    tile_kernel = model.distortion_tile

    def tile(seed, M, a, b, *rest):
        t0 = _t.perf_counter()
        out = tile_kernel(seed, M, a, b, *rest)
        state["tile_s"] += _t.perf_counter() - t0
        key = (int(seed), hash(M.tobytes()), int(a), int(b))
        if key in state["first"]:  # built again: how many other woods had tiles built since
            since = {w for w in state["order"][state["first"][key] + 1:] if w != key[:2]}
            state["woods_between"][len(since)] += 1
        else:
            state["first"][key] = len(state["order"])
        state["order"].append(key[:2])
        state["tiles"][key] += 1
        return out

    def timing(f, seconds, calls=None):
        """``f`` adding its seconds to state[seconds] and counting its calls in state[calls]."""
        def timed(*args, **kwargs):
            t0 = _t.perf_counter()
            out = f(*args, **kwargs)
            state[seconds] += _t.perf_counter() - t0
            if calls:
                state[calls] += 1
            return out
        return timed

    march = wood_surface.march
    from pipeline.optics._surface_march import COUNTS, PURPOSES
    state["evaluations"] = dict.fromkeys(PURPOSES, 0)
    state["interfaces"] = 0

    def timed_march(*args):
        work = args[-1]  # the slice's work buffer: its counts by purpose before and after
        before = work[COUNTS:].copy()
        t0 = _t.perf_counter()
        out = march(*args)
        state["march_s"] += _t.perf_counter() - t0
        state["marches"] += 1
        for name, a, b in zip(PURPOSES, before, work[COUNTS:]):
            state["evaluations"][name] += int(b - a)
        return out

    walls = wood_surface.WoodSurface.march_walls

    def counted_walls(self, *args, **kwargs):
        out = walls(self, *args, **kwargs)
        state["interfaces"] += int(out["events"].sum())
        return out

    model.distortion_tile = tile
    wood_surface.region_context = timing(region.region_context, "region_s", "regions")
    wood_surface.march = timed_march
    wood_surface.warm_regions = timing(wood_surface.warm_regions, "warm_s")
    wood_surface.WoodSurface.march_walls = counted_walls
    import builtins
    builtins._twray_census = state
    return True


def _read():
    import builtins
    s = builtins._twray_census
    counts = list(s["tiles"].values())
    return {"tiles_built": sum(counts), "distinct_tiles": len(counts),
            "tiles_built_again": sum(c - 1 for c in counts),
            # of those, how many by the number of other woods that had tiles built in between
            "tiles_again_after_other_woods": dict(sorted(s["woods_between"].items())), "woods": len(set(s["order"])),
            # stretches of tiles built for one wood: as many as woods when each wood's shards ran in a row
            "wood_stretches": sum(1 for i, w in enumerate(s["order"]) if i == 0 or w != s["order"][i - 1]),
            "tile_s": round(s["tile_s"], 2),
            "regions": s["regions"], "region_s": round(s["region_s"], 2), "warm_regions_s": round(s["warm_s"], 2),
            "march_s": round(s["march_s"], 2), "marches": s["marches"], "interfaces": s["interfaces"],
            **{f"evaluations_{k}": v for k, v in s["evaluations"].items()}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("studies", nargs="+")
    ap.add_argument("--scale", default="paper")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default="results/bench.json")
    ap.add_argument("--tile-budget", type=int, help="tiles a worker keeps beside the wood in use (default: the model's)")
    args = ap.parse_args(argv)
    from pipeline.cluster import graph_client

    # The cluster `twray study` would start itself (its workers' memory settings included).
    client, cluster = graph_client("study", workers=args.workers, threads=1)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            client.run(_install, args.tile_budget)
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "pipeline", "study", *args.studies, "--scale", args.scale,
                            "--yes", "--scheduler", cluster.scheduler_address, "--cache", str(Path(tmp) / "cache"),
                            "--results", str(Path(tmp) / "results"), "--quiet"], check=True)
            wall = time.perf_counter() - t0
            per_worker = list(client.run(_read).values())
    finally:
        client.close()
        cluster.close()
    total = {k: round(sum(w[k] for w in per_worker), 2) for k in per_worker[0]
             if isinstance(per_worker[0][k], (int, float))}
    out = {"studies": args.studies, "scale": args.scale, "workers": args.workers, "wall_s": round(wall, 1),
           "tile_budget": args.tile_budget,
           "per_worker": per_worker, "total": total}
    write_section(args.out, "study_census", out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
