"""`exact` on generated wood: speed beside the voxel methods, the 1.5 mm × 1000-ray trace cold,
and the refinement check at 1000 rays × 1 mm (docs/methods.md#the-exact-method).

Writes the "exact" section of results/bench.json:
- per_interface: µs per interface on 0.25 mm of birch (200 rays, ΔRI 0.01) for `exact`,
  `fast` and `accurate`, cold (no wood or distortion tile cached, kernels compiled) and warm
  (the same trace again in the same process), on one core;
- lazy_1_5mm: 1000 rays through 1.5 mm of birch, cold, on 2 threads: seconds, of which building
  the first region (before any ray is traced), the distortion tiles computed and their seconds
  summed over threads, the process's CPU seconds, interfaces, evaluations per interface, peak RSS;
  and the same trace with `accurate` (its wood generated as the rays reach it), in the same run;
- refinement: 1000 rays × 1 mm traced twice, the second time with every step and tolerance
  halved (the clearance steps, the probe, the bracket): rays that come out bit for bit the same,
  and how far the others part.
- lattices: 1000 rays through 300 µm of each reference lattice (ΔRI 0.03, warm, one core): µs per
  interface of `exact` (the march that traces the wood) and of the independent exact tracer, and
  how many exit directions agree to 1e-9 rad.
- per_interface_1mm: µs per interface of `exact` on 1 mm of birch (300 rays, ΔRI 0.01), warm, one
  core, the measure of the goal table in results/BENCH.md;
- along_1mm: the same scene with the steps proven along the ray (``wood_surface.ALONG``) and with
  the balls alone, interleaved in one process: µs an interface (CPU), evaluations and steps an
  interface, and how many exit directions part;
- first_compile: `twray trace --preset birch --thickness-mm 0.1 --rays 20` with `exact` and with
  `accurate` into an empty kernel cache (a first run of a checkout's sources on a machine: it
  compiles the kernels), then the same again (kernels loaded): wall and CPU seconds of each, the
  measure behind `limits.COMPILE_CPU_S`;
- whole_process: `twray trace --preset birch --thickness-mm 1 --rays 200` as whole processes with
  `exact` and with `accurate` (kernels compiled by a first run of each, the second timed);
- normals: µs per normal at the primitives listed at random points of 0.25 mm of birch and of
  balsa (warm, one core), by the analytic gradient (one call: the march's normal since `exact` 4) and by
  the central differences it took before (six evaluations of the primitive, step 1e-6 µm), and the
  angle between the two.
Each part runs in a fresh process so that "cold" means it.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

SNIPPETS = {}


def _part(name):
    def deco(f):
        SNIPPETS[name] = f
        return f
    return deco


def _setup():
    from pipeline.microstructure.model import _tile  # noqa: F401  (the tile cache starts empty)
    from pipeline.optics.media import wood_medium
    from pipeline.optics.rays import square_beam
    from pipeline.optics.settings import Optics, settings_for
    from pipeline.optics.trace import trace
    from pipeline.params import build_params
    return wood_medium, square_beam, Optics, settings_for, trace, build_params


def _compile(method):
    """Compile the kernels on a tiny trace far away (other tiles, other chunks)."""
    wood_medium, square_beam, Optics, settings_for, trace, build_params = _setup()
    s = settings_for(method)
    m = wood_medium(build_params("birch"), seed=99, thickness_um=10.0, voxel_um=0.5, settings=s)
    trace(m, square_beam(4, 10.0, (5e4, 5e4), seed=1), Optics(1.53, 1.52), s)


def _timed(f, times: list):
    """``f`` appending the seconds of each call to ``times`` (list.append is atomic: tiles and regions
    are built on several threads)."""
    def timed(*a, **k):
        t0 = time.perf_counter()
        try:
            return f(*a, **k)
        finally:
            times.append(time.perf_counter() - t0)
    return timed


@_part("per_interface")
def per_interface(method: str) -> dict:
    wood_medium, square_beam, Optics, settings_for, trace, build_params = _setup()
    _compile(method)
    s = settings_for(method)
    beam = square_beam(200, 150.0, seed=1)
    out = {"method": method, "rays": 200, "thickness_mm": 0.25}
    built = []
    if method == "exact":  # the regions' share of the time, apart from the march's
        import pipeline.optics.wood_surface as ws
        ws.region_context = _timed(ws.region_context, built)
    for phase in ("cold", "warm"):
        m = wood_medium(build_params("birch"), seed=1, thickness_um=250.0, voxel_um=0.5, settings=s)
        built.clear()
        t0 = time.perf_counter()
        r = trace(m, beam, Optics(1.53, 1.52), s)
        dt = time.perf_counter() - t0
        ev = max(1, int(r.events.sum()))
        out[phase] = {"seconds": dt, "interfaces": ev, "us_per_interface": 1e6 * dt / ev}
        if method == "exact":
            n = sum(m.evaluations.values())
            out[phase].update({
                "region_seconds": sum(built), "regions": len(built),
                "us_per_interface_march": 1e6 * (dt - sum(built)) / ev, "evaluations_per_interface": n / ev,
                "ns_per_evaluation": 1e9 * (dt - sum(built)) / n,
                "evaluations_by_purpose_per_interface": {k: v / ev for k, v in m.evaluations.items()}})
    return out


@_part("lazy_1_5mm")
def lazy(_: str) -> dict:
    from pipeline.microstructure import region
    wood_medium, square_beam, Optics, settings_for, trace, build_params = _setup()
    _compile("exact")
    s = settings_for("exact")
    built, tiles = [], []
    import pipeline.microstructure.model as model
    import pipeline.optics.wood_surface as ws
    ws.region_context = _timed(region.region_context, built)
    model.distortion_tile = _timed(model.distortion_tile, tiles)
    m = wood_medium(build_params("birch"), seed=1, thickness_um=1500.0, voxel_um=0.5, settings=s, threads=2)
    t0, c0 = time.perf_counter(), time.process_time()
    r = trace(m, square_beam(1000, 150.0, seed=1), Optics(1.53, 1.52), s)
    dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    ev = int(r.events.sum())
    # Regions after the first are built while other rays are traced: their share of the wall clock
    # is not separable, so the tiles' time is given summed over the threads that computed them.
    return {"method": "exact", "rays": 1000, "thickness_mm": 1.5, "threads": 2, "seconds": dt,
            "cpu_seconds": cpu, "seconds_first_region": built[0], "tiles": len(tiles),
            "tile_seconds_summed": sum(tiles),
            "regions": len(built), "interfaces": ev, "us_per_interface_wall": 1e6 * dt / ev,
            "evaluations_per_interface": float(r.extras["evaluations"].sum() / ev),
            "evaluations_by_purpose_per_interface": {k: v / ev for k, v in m.evaluations.items()},
            "surfaces_passed_per_ray": float(r.extras["passes"].mean()),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "voxels_generated": 0}


@_part("lazy_1_5mm_voxels")
def lazy_voxels(method: str) -> dict:
    wood_medium, square_beam, Optics, settings_for, trace, build_params = _setup()
    _compile(method)
    s = settings_for(method)
    m = wood_medium(build_params("birch"), seed=1, thickness_um=1500.0, voxel_um=0.5, settings=s, threads=2)
    t0 = time.perf_counter()
    r = trace(m, square_beam(1000, 150.0, seed=1), Optics(1.53, 1.52), s)
    dt = time.perf_counter() - t0
    return {"method": method, "rays": 1000, "thickness_mm": 1.5, "threads": 2, "seconds": dt,
            "interfaces": int(r.events.sum()), "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


@_part("refinement")
def refinement(_: str) -> dict:
    from pipeline.optics.wood_surface import WoodSurface
    wood_medium, square_beam, Optics, settings_for, trace, build_params = _setup()
    p = build_params("birch")
    beam = square_beam(1000, 150.0, seed=1)
    s = settings_for("exact")
    a = trace(WoodSurface(p, thickness_um=1000.0, seed=1, threads=2), beam, Optics(1.53, 1.52), s)
    b = trace(WoodSurface(p, thickness_um=1000.0, seed=1, threads=2, hit=5e-10, tol=5e-10, step_scale=0.5),
              beam, Optics(1.53, 1.52), s)
    diff = np.linalg.norm(a.direction - b.direction, axis=1)  # ~ the angle [rad]
    same = np.all(a.direction == b.direction, axis=1) & np.all(a.position == b.position, axis=1)
    return {"rays": 1000, "thickness_mm": 1.0, "interfaces_per_ray": float(a.events.mean()),
            "rays_bit_identical": int(same.sum()), "rays_same_interfaces": int((a.events == b.events).sum()),
            "rays_within_1e-10_rad": int((diff <= 1e-10).sum()), "largest_change_rad": float(diff.max()),
            "evaluations_ratio": float(b.extras["evaluations"].sum() / a.extras["evaluations"].sum()),
            "fwhm_r_deg": [float(_fwhm(a)), float(_fwhm(b))]}


@_part("lattices")
def lattices(_: str) -> dict:
    from pipeline.optics.references import REFERENCES, reference
    _, square_beam, Optics, settings_for, trace, _ = _setup()
    beam = square_beam(1000, 150.0, seed=1, direction=(0.2, 1.0, 0.1))
    d = beam.unit_directions()
    out = []
    for name in REFERENCES:
        lat = reference(name, pitch_um=14.5, wall_um=2.0, jitter=0.1).lattice(1)
        trace(lat.slab(20.0), beam[:10], Optics(1.52, 1.49), settings_for("exact"))  # compiled
        lat.trace_independently(beam.origins[:10], d[:10], n_wall=1.52, n_poly=1.49, thickness_um=20.0)
        t0 = time.perf_counter()
        a = trace(lat.slab(300.0), beam, Optics(1.52, 1.49), settings_for("exact"))
        t1 = time.perf_counter()
        b = lat.trace_independently(beam.origins, d, n_wall=1.52, n_poly=1.49, thickness_um=300.0)
        t2 = time.perf_counter()
        ang = np.arctan2(np.linalg.norm(np.cross(a.direction, b.direction), axis=1),
                         np.einsum("ij,ij->i", a.direction, b.direction))
        ev = max(1, int(a.events.sum()))
        out.append({"reference": name, "interfaces_per_ray": float(a.events.mean()),
                    "us_per_interface_exact": 1e6 * (t1 - t0) / ev, "us_per_interface_independent": 1e6 * (t2 - t1) / ev,
                    "evaluations_per_interface": float(a.extras["evaluations"].sum() / ev),
                    "rays_within_1e-9_rad": int((ang <= 1e-9).sum()), "rays_same_interfaces": int((a.events == b.events).sum())})
    return {"rays": 1000, "thickness_um": 300.0, "pitch_um": 14.5, "wall_um": 2.0, "jitter": 0.1, "rows": out}


@_part("per_interface_1mm")
def per_interface_1mm(_: str) -> dict:
    wood_medium, square_beam, Optics, settings_for, trace, build_params = _setup()
    _compile("exact")
    s = settings_for("exact")
    beam = square_beam(300, 150.0, seed=1)
    best = None
    for _ in range(3):  # the first builds the regions and warms the memos; the best of the others
        m = wood_medium(build_params("birch"), seed=1, thickness_um=1000.0, voxel_um=0.5, settings=s)
        t0 = time.perf_counter()
        r = trace(m, beam, Optics(1.50, 1.49), s)
        dt = time.perf_counter() - t0
        best = dt if best is None else min(best, dt)
    ev = int(r.events.sum())
    # The last trace's steps by what bounded each (the same rays each time, so one trace's counts).
    return {"rays": 300, "thickness_mm": 1.0, "delta_ri": 0.01, "interfaces": ev,
            "us_per_interface": round(1e6 * best / ev, 2),
            "evaluations_per_interface": round(sum(m.evaluations.values()) / ev, 3),
            "steps_by_bound_per_interface": _bounds(m.steps, ev)}


@_part("along_1mm")
def along_1mm(_: str) -> dict:
    """The march with steps proven along the ray (``along``, `exact` 5's) against the balls alone
    (`exact` 4's), on the scene of per_interface_1mm, interleaved in one process (CPU seconds, best
    of three each, twice over), and how far the exit directions part."""
    import pipeline.optics.wood_surface as ws
    wood_medium, square_beam, Optics, settings_for, trace, build_params = _setup()
    _compile("exact")
    s = settings_for("exact")
    beam = square_beam(300, 150.0, seed=1)
    best, last = {}, {}
    default = ws.ALONG
    for along in (False, True, False, True):
        ws.ALONG = along
        for _ in range(3):
            m = wood_medium(build_params("birch"), seed=1, thickness_um=1000.0, voxel_um=0.5, settings=s)
            c0 = time.process_time()
            r = trace(m, beam, Optics(1.50, 1.49), s)
            dt = time.process_time() - c0
            best[along] = min(best.get(along, dt), dt)
        last[along] = (r, m)
    ws.ALONG = default
    out = {"rays": 300, "thickness_mm": 1.0, "delta_ri": 0.01}
    for along, name in ((False, "balls"), (True, "along")):
        r, m = last[along]
        ev = int(r.events.sum())
        out[name] = {"interfaces": ev, "us_per_interface": round(1e6 * best[along] / ev, 2),
                     "evaluations_per_interface": round(sum(m.evaluations.values()) / ev, 3),
                     "evaluations_by_purpose_per_interface": {k: round(v / ev, 3) for k, v in m.evaluations.items()},
                     "steps_per_interface": round(sum(m.steps[k] for k in ("own", "others", "secant", "away", "regime",
                                                                            "inside", "probe", "again", "cross")) / ev, 3),
                     "steps_by_bound_per_interface": _bounds(m.steps, ev)}
    a, b = last[False][0], last[True][0]
    ang = np.arccos(np.clip((a.direction * b.direction).sum(axis=1), -1.0, 1.0))
    out["time_ratio"] = round(best[True] / best[False], 3)
    out["rays_moved"] = {"over_1e-9_rad": int((ang > 1e-9).sum()), "over_1e-6_rad": int((ang > 1e-6).sum()),
                         "over_1e-3_rad": int((ang > 1e-3).sum()),
                         "interface_counts_differ": int((a.events != b.events).sum())}
    return out


def _bounds(steps: dict, interfaces: int) -> dict:
    """Steps an interface by what bounded them; A's own clearance for a reason the march does not
    count (no secant yet, mostly: A's first step or a new segment) is what the others leave."""
    out = {k: v / interfaces for k, v in steps.items()}
    out["own_no_secant"] = out["own"] - out["own_free"] - out["own_past_others"] - out["own_again"]
    return {k: round(v, 3) for k, v in out.items()}


def _twray_trace(args: list, cwd, env=None) -> tuple:
    """`twray trace ARGS --quiet` as a whole process in ``cwd``: (wall seconds, CPU seconds)."""
    import shutil
    twray = shutil.which("twray") or str(Path(sys.executable).with_name("twray"))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run([twray, "trace", *args, "--quiet"], check=True, capture_output=True, cwd=cwd, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


@_part("whole_process")
def whole_process(_: str) -> dict:
    import shutil
    import tempfile
    args = ["--preset", "birch", "--thickness-mm", "1", "--delta-ri", "0.01", "--rays", "200"]
    out = {"command": "twray trace " + " ".join(args) + " --quiet"}
    with tempfile.TemporaryDirectory() as tmp:
        for method in ("exact", "accurate"):
            for _ in range(2):  # the second timed: kernels compiled by the first
                shutil.rmtree(Path(tmp) / f"{method}.zarr", ignore_errors=True)
                wall, _cpu = _twray_trace(args + ["--method", method, "--out", str(Path(tmp) / f"{method}.zarr")], tmp)
            out[f"{method}_s"] = round(wall, 2)
    out["accurate_over_exact"] = round(out["accurate_s"] / out["exact_s"], 2)
    return out


@_part("first_compile")
def first_compile(_: str) -> dict:
    import os
    import tempfile
    args = ["--preset", "birch", "--thickness-mm", "0.1", "--delta-ri", "0.01", "--rays", "20"]
    out = {"command": "twray trace " + " ".join(args) + " --quiet"}
    with tempfile.TemporaryDirectory() as tmp:
        for method in ("exact", "accurate"):
            env = {**os.environ, "NUMBA_CACHE_DIR": str(Path(tmp) / method)}
            for run in ("cold", "warm"):
                wall, cpu = _twray_trace(args + ["--method", method], tmp, env)
                out[f"{method}_{run}_s"] = round(wall, 1)
                out[f"{method}_{run}_cpu_s"] = round(cpu, 1)
            out[f"{method}_compile_cpu_s"] = round(out[f"{method}_cold_cpu_s"] - out[f"{method}_warm_cpu_s"], 1)
    return out


@_part("normals")
def normals(_: str) -> dict:
    from numba import njit

    from pipeline.microstructure import region as R
    from pipeline.microstructure.surface import MAX_PRIMS, N_COLS, P_REACH, evaluate_at, find_row, new_cache
    from pipeline.microstructure.surface_gradient import gradient_at
    from pipeline.params import build_params

    @njit
    def analytic(pts, keys, ctx, cache, out):
        ok = 0
        for i in range(pts.shape[0]):
            ok += gradient_at(pts[i, 0], pts[i, 1], pts[i, 2], ctx, keys[i], cache, out[i])
        return ok

    @njit
    def differences(pts, keys, ctx, Q, cache, h, out):
        for i in range(pts.shape[0]):
            for q in range(3):
                g = np.zeros(2)
                for j in range(2):
                    x = pts[i].copy()
                    x[q] += h if j == 0 else -h
                    _, m = evaluate_at(x[0], x[1], x[2], 0.0, ctx, Q, cache, keys[i])
                    r = find_row(Q, m, keys[i])
                    g[j] = Q[r, 5] if r >= 0 else np.nan
                out[i, q] = (g[0] - g[1]) / (2.0 * h)

    result = {}
    for preset in ("birch", "balsa"):
        p = build_params(preset)
        ctx = R.context_tuple(R.region_context(p, 3, 250.0, (-60.0, 60.0), (-60.0, 60.0)))
        rng = np.random.default_rng(2)
        P = np.empty((MAX_PRIMS, N_COLS))
        cache = new_cache()
        pts, keys = [], []
        for x in np.column_stack([rng.uniform(-50, 50, 3000), rng.uniform(1, 249, 3000), rng.uniform(-50, 50, 3000)]):
            _, n = evaluate_at(x[0], x[1], x[2], 0.0, ctx, P, cache, np.zeros(5))
            for row in P[:n]:
                if row[0] != P_REACH and row[6] < 1e200:
                    pts.append(x)
                    keys.append(row[:5].copy())
        pts, keys = np.array(pts), np.array(keys)
        a = np.zeros((len(pts), 3))
        d = np.zeros((len(pts), 3))
        analytic(pts[:2], keys[:2], ctx, cache, a[:2])
        differences(pts[:2], keys[:2], ctx, P, cache, 1e-6, d[:2])
        ta, td = [], []
        for _ in range(5):
            t0 = time.perf_counter()
            analytic(pts, keys, ctx, cache, a)
            ta.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            differences(pts, keys, ctx, P, cache, 1e-6, d)
            td.append(time.perf_counter() - t0)
        cos = np.sum(a * d, 1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(d, axis=1))
        angle = np.arccos(np.clip(cos, -1.0, 1.0))
        result[preset] = {"normals": len(pts), "analytic_us": round(1e6 * min(ta) / len(pts), 3),
                          "differences_us": round(1e6 * min(td) / len(pts), 3),
                          "speedup": round(min(td) / min(ta), 1),
                          "angle_rad_median": float(np.median(angle)), "angle_rad_p99": float(np.quantile(angle, 0.99)),
                          "angle_rad_max": float(angle.max())}
    return result


def _fwhm(res):
    from pipeline.summary import summarize
    return summarize(res, n_boot=2)["fwhm_r_deg"]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="results/bench.json")
    ap.add_argument("--part")
    ap.add_argument("--method", default="exact")
    ap.add_argument("--only", help="comma-separated parts to run again, the others kept from --out")
    args = ap.parse_args()
    if args.part:  # one part, in this (fresh) process
        print(json.dumps(SNIPPETS[args.part](args.method)))
        return
    from _bench_json import write_section

    def fresh(part, method="exact"):
        out = subprocess.run([sys.executable, __file__, "--part", part, "--method", method], check=True,
                             capture_output=True, text=True).stdout
        return json.loads(out.strip().splitlines()[-1])

    parts = {"per_interface": lambda: [fresh("per_interface", m) for m in ("exact", "fast", "accurate")],
             "lazy_1_5mm": lambda: fresh("lazy_1_5mm"),
             "lazy_1_5mm_accurate": lambda: fresh("lazy_1_5mm_voxels", "accurate"),
             "refinement": lambda: fresh("refinement"), "lattices": lambda: fresh("lattices"),
             "normals": lambda: fresh("normals"), "per_interface_1mm": lambda: fresh("per_interface_1mm"),
             "along_1mm": lambda: fresh("along_1mm"),
             "whole_process": lambda: fresh("whole_process"), "first_compile": lambda: fresh("first_compile")}
    only = args.only.split(",") if args.only else list(parts)
    unknown = sorted(set(only) - set(parts))
    if unknown:
        ap.error(f"`--only` must name parts among {', '.join(parts)}, got {', '.join(unknown)}")
    path = Path(args.out)
    result = json.loads(path.read_text()).get("exact", {}) if path.exists() and args.only else {}
    result.update({name: parts[name]() for name in only})
    write_section(args.out, "exact", result)


if __name__ == "__main__":
    main()
