"""Table 1 as a study graph: cold and warm wall time, and where a paper-scale scene spends it.

Writes the "study" section of results/bench.json:
- table1_small: every Table 1 study at --scale small in a fresh cache, then
  again unchanged (the warm run computes nothing), as one ``twray study`` call;
- paper_scene: a slice of one paper-scale scene (1 mm of birch, ΔRI = 0.03,
  accurate), traced in this process, split into wood generation and tracing,
  with the wood chunks it needed per ray;
- workers: Table 1 at --scale small, cold, on 1 worker of 1 thread, 1 worker
  of 2 threads and 2 workers of 1 thread;
- thickness: one cold trace (accurate, 200 rays, birch, ΔRI 0.01) through
  0.25, 0.5 and 1 mm: seconds, chunks generated, interfaces per ray;
- table1_quick: the same at --scale quick (`make table1`, the quick start: the paper's
  samples and woods, a twentieth of the rays), cold and warm;
- table1_paper (only with --paper, which runs nothing else and keeps the
  other keys): every Table 1 study at paper scale in a fresh cache, as
  `make table1` runs it: wall and CPU seconds of the whole command;
  ``--small`` likewise reruns table1_small alone.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import xarray as xr

from _bench_json import write_section

from pipeline.microstructure.store import WoodChunkStore
from pipeline.optics.sources import WoodSource
from pipeline.optics.rays import Beam, square_beam
from pipeline.optics.settings import settings_for
from pipeline.optics.voxels import trace_in_voxels
from pipeline.params import build_params

ROOT = Path(__file__).resolve().parent.parent


def _table1_cmd(cache: Path, results: Path, *extra, scale: str = "small") -> list:
    files = sorted(str(p) for p in (ROOT / "studies" / "table1").glob("*.yaml"))
    return [sys.executable, "-m", "pipeline", "study", *files, "--scale", scale,
            "--cache", str(cache), "--results", str(results), "--quiet", *extra]


def workers(tmp: Path) -> dict:
    out = {}
    for w, t in ((1, 1), (1, 2), (2, 1)):
        name = f"{w}_workers_{t}_threads"
        t0 = time.perf_counter()
        subprocess.run(_table1_cmd(tmp / f"cache-{name}", tmp / f"results-{name}", "--workers", str(w),
                                   "--threads", str(t)), check=True, capture_output=True)
        out[name + "_s"] = round(time.perf_counter() - t0, 1)
    out["speedup_2_cores"] = round(out["1_workers_1_threads_s"] / min(out["1_workers_2_threads_s"],
                                                                      out["2_workers_1_threads_s"]), 2)
    return out


def thickness() -> dict:
    out = {}
    params = build_params("birch")
    for mm in (0.25, 0.5, 1.0):
        source = WoodSource(params, thickness_um=1000.0 * mm, voxel_um=0.25, seed=7)
        beam = square_beam(200, 150 / 0.25, seed=7)
        t0 = time.perf_counter()
        r = trace_in_voxels(source, beam, n_wall=1.50, n_poly=1.49, settings=settings_for("accurate", refine=1), seed=7)
        out[f"{mm:g}_mm"] = {"seconds": round(time.perf_counter() - t0, 2), "chunks_generated": len(source.distinct),
                             "interfaces_per_ray": round(float(r.events.mean()), 1)}
    return out


def table1_small(tmp: Path, scale: str = "small") -> dict:
    cmd = _table1_cmd(tmp / "cache", tmp / "results", scale=scale)
    out = {}
    for run in ("cold", "warm"):
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True)
        out[f"{run}_s"] = round(time.perf_counter() - t0, 2)
    out["cold_over_warm"] = round(out["cold_s"] / out["warm_s"], 1)
    return out


def table1_paper(tmp: Path) -> dict:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(_table1_cmd(tmp / "cache", tmp / "results", "--yes", scale="paper"), check=True,
                   capture_output=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    t0 = time.perf_counter()  # again: every entry cached
    subprocess.run(_table1_cmd(tmp / "cache", tmp / "results", "--yes", scale="paper"), check=True,
                   capture_output=True)
    warm = time.perf_counter() - t0
    woods = {}
    for path in sorted((tmp / "results").glob("study-*.zarr")):
        with xr.open_zarr(path, consolidated=False) as ds:
            woods[path.stem] = ds.sizes.get("realisation", 1)
    return {"cold_s": round(wall, 1), "cpu_s": round(cpu, 1), "warm_s": round(warm, 2), "realisations": woods,
            "how": "`benchmarks/bench_study.py --paper`: every Table 1 study at paper scale (`exact`, 1000 rays a "
                   "wood, as many woods as its target asks for) in a fresh cache, kernels compiled, on 2 cores"}


def paper_scene(tmp: Path, n_rays: int) -> dict:
    params = build_params("birch")
    store = WoodChunkStore(tmp / "wood.zarr", params, seed=1, voxel_um=0.5)
    spent = [0.0]
    get_many = store.get_many  # what the tracer's chunk cache calls

    def timed(indices):
        t = time.perf_counter()
        data = get_many(indices)
        spent[0] += time.perf_counter() - t
        return data

    store.get_many = timed
    source = WoodSource(params, thickness_um=1000.0, voxel_um=0.5, seed=1, store=store)
    beam = square_beam(1000, 300, (0.0, 0.0), seed=1)
    part = Beam(beam.origins[:n_rays], beam.direction, beam.ray_ids[:n_rays])
    t0 = time.perf_counter()
    r = trace_in_voxels(source, part, n_wall=1.52, n_poly=1.49, settings=settings_for("accurate"), seed=1)
    total = time.perf_counter() - t0
    return {"rays": n_rays, "seconds": round(total, 1), "wood_seconds": round(spent[0], 1),
            "chunks_generated": store.generated, "chunks_per_ray": round(store.generated / n_rays, 1),
            "voxels_per_ray": round(store.generated * 64**3 / n_rays),
            "interfaces_per_ray": round(float(r.events.mean()), 1),
            "us_per_interface_tracing": round((total - spent[0]) / r.events.sum() * 1e6, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/bench.json")
    ap.add_argument("--rays", type=int, default=50, help="rays of the paper-scale slice")
    ap.add_argument("--paper", action="store_true",
                    help="only time Table 1 at paper scale, cold and warm (about 20 min on 2 cores)")
    ap.add_argument("--small", action="store_true",
                    help="only time Table 1 at small scale, cold and warm (a few minutes)")
    ap.add_argument("--quick", action="store_true",
                    help="only time Table 1 at quick scale (`make table1`), cold and warm (a few minutes)")
    args = ap.parse_args()
    if args.paper or args.small or args.quick:
        out = Path(args.out)
        section = json.loads(out.read_text()).get("study", {}) if out.exists() else {}
        with tempfile.TemporaryDirectory() as tmp:
            if args.paper:
                # Earlier measurements kept beside it (other methods and versions: dict entries).
                history = {k: v for k, v in section.get("table1_paper", {}).items() if isinstance(v, dict)}
                section["table1_paper"] = {**table1_paper(Path(tmp)), "method": "exact", **history}
            elif args.quick:
                section["table1_quick"] = {**table1_small(Path(tmp), "quick"), "method": "exact"}
            else:
                section["table1_small"] = {**table1_small(Path(tmp)), "method": "exact"}
        write_section(args.out, "study", section)
        return
    with tempfile.TemporaryDirectory() as tmp:
        result = {"table1_small": {**table1_small(Path(tmp)), "method": "exact"},
                  "table1_quick": {**table1_small(Path(tmp) / "quick", "quick"), "method": "exact"},
                  "paper_scene": paper_scene(Path(tmp), args.rays),
                  "workers": workers(Path(tmp)),
                  "thickness": thickness(),
                  "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)}
    out = Path(args.out)
    earlier = json.loads(out.read_text()).get("study", {}) if out.exists() else {}
    for key in ("table1_paper", "table1_paper_method", "experiment_paper", "fibre_tips_paper"):  # measured by other runs
        if key in earlier:
            result[key] = earlier[key]
    write_section(args.out, "study", result)


if __name__ == "__main__":
    main()
