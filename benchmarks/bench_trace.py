"""Tracer speed and accuracy per preset, and a 1.5 mm lazy birch trace.

Writes the "trace" section of results/bench.json:
- rods: error of each preset against the exact deflection law of a
  voxelised rod (R = 30 voxels, 1.50 in 1.49, random sub-voxel centres);
- tubes: the same for tubes (outer R = 30 voxels) with walls of 1 to 6
  voxels, thin walls being where voxel normals are hardest;
- sheets: rays through flat sheets of wall (or polymer) 1-2 voxels thick,
  tilted 20-70° from the beam, which leave exactly undeflected;
- birch: rays/s and interfaces/s on a 0.25 mm birch block held in memory, and
  the speed-up per interface of fast/accurate over paper, end to end and
  without the time spent reading and bit-packing the block's chunks; and the
  same for the block index-matched (no normal needed): the traversal and the
  reading alone, the bound on any normal estimator's speed-up;
- normal_estimators: the normal estimators alone on the same birch interface
  points (paper's scikit-learn SVM on its 6³ box against fast's and accurate's
  Gaussian windows with their Newton steps), without traversal or loading;
- lazy_1_5mm: 1000 rays through 1.5 mm of lazily generated birch: time,
  peak RSS, chunks generated against the chunks of the whole paper sample,
  voxels generated against voxels read; again generating on 2 threads.
"""

from __future__ import annotations

import argparse
import math
import resource
import time

import numpy as np
from _bench_json import write_section
from numba import njit
from scipy import stats

from pipeline.summary import summarize
from pipeline.microstructure.model import generate_block
from pipeline.optics import _normals
from pipeline.optics.sources import ArraySource, ChunkCache, WoodSource
from pipeline.optics.rays import Beam, square_beam
from pipeline.optics.settings import settings_for
from pipeline.optics.voxels import svm_normal, trace_in_voxels
from pipeline.optics.validation import (rod_deflection_deg, tube_deflection_deg, voxelised_rod,
                                       voxelised_sheet, voxelised_tube)
from pipeline.params import build_params, make_grid

M_REL = 1.50 / 1.49


def _across(vol, c0: float, b: np.ndarray, method: str):
    """Rays along +T at impact parameters ``b`` from R = c0 through a cylinder volume (axis along L)."""
    nn = vol.shape[0]
    origins = np.column_stack([c0 + b, np.zeros_like(b), np.full_like(b, 16.0)])
    return trace_in_voxels(ArraySource(vol, chunks=(nn, nn, 32)),
                      Beam(origins, np.array([0.0, 1.0, 0.0]), np.arange(b.size)),
                      n_wall=1.50, n_poly=1.49, settings=settings_for(method))


def rod_errors(method: str, rays_per_rod: int, n_rods: int = 4, R: float = 30.0, seed: int = 0):
    rng = np.random.default_rng(seed)
    got, exact, events, seconds = [], [], 0, 0.0
    for off in rng.uniform(0, 1, size=(n_rods, 2)):
        c0, c1 = R + 20 + off[0], R + 20 + off[1]
        vol = voxelised_rod(R, (c0, c1), int(2 * R + 42))
        b = rng.uniform(-R, R, rays_per_rod)
        t0 = time.perf_counter()
        res = _across(vol, c0, b, method)
        seconds += time.perf_counter() - t0
        events += int(res.events.sum())
        got.append(res.theta_r)
        exact.append(rod_deflection_deg(b, R, M_REL))
    got, exact = np.concatenate(got), np.concatenate(exact)
    return {
        "rays": int(got.size),
        "rms_error_deg": float(np.sqrt(np.mean((got - exact) ** 2))),
        "median_abs_error_deg": float(np.median(np.abs(got - exact))),
        "haze": float(np.mean(np.abs(got) > 2.5)),
        "haze_exact_same_rays": float(np.mean(np.abs(exact) > 2.5)),
        "ks_statistic": float(stats.ks_2samp(got, exact).statistic),
        "us_per_interface": 1e6 * seconds / max(events, 1),
    }


def tube_errors(method: str, wall: float, rays_per_tube: int = 600, n_tubes: int = 6, R: float = 30.0,
                seed: int = 0):
    """Exit-angle errors through voxelised tubes against their exact law (rays that the
    exact tube reflects totally at its lumen left out)."""
    rng = np.random.default_rng(seed)
    err, thin, events = [], 0, 0
    for off in rng.uniform(0, 1, size=(n_tubes, 2)):
        c0, c1 = R + 20 + off[0], R + 20 + off[1]
        vol = voxelised_tube(R, wall, (c0, c1), int(2 * R + 42))
        b = rng.uniform(-R, R, rays_per_tube)
        exact = tube_deflection_deg(b, R, wall, M_REL)
        b, exact = b[~np.isnan(exact)], exact[~np.isnan(exact)]
        res = _across(vol, c0, b, method)
        t = res.transmitted
        err.append(np.abs(res.theta_r[t] - exact[t]))
        thin += int(res.extras["thin_wall_normals"].sum())
        events += int(res.events.sum())
    e = np.concatenate(err)
    return {"wall_vox": wall, "rays": int(e.size), "median_abs_error_deg": float(np.median(e)),
            "share_above_2_deg": float(np.mean(e > 2.0)), "thin_wall_normals_share": thin / max(events, 1)}


def sheet_errors(method: str, thickness: float, phase: int = 1, tilts=(20.0, 45.0, 60.0, 70.0),
                 rays_per_tilt: int = 400, seed: int = 0):
    """Deflection through flat sheets, exactly 0 (parallel faces), at tilts of their normal from +T."""
    rng = np.random.default_rng(seed)
    out = []
    n = rays_per_tilt // 4
    for tilt in tilts:
        dev = []
        for off in rng.uniform(0, 1, 4):
            vol = voxelised_sheet(tilt, off, thickness, phase=phase)
            origins = np.column_stack([rng.uniform(44, 84, n), np.zeros(n), np.full(n, 16.0)])
            res = trace_in_voxels(ArraySource(vol, chunks=(128, 128, 32)),
                             Beam(origins, np.array([0.0, 1.0, 0.0]), np.arange(n)),
                             n_wall=1.50, n_poly=1.49, settings=settings_for(method))
            t = res.transmitted
            dev.append(np.hypot(res.theta_r[t], res.theta_l[t]))
        d = np.concatenate(dev)
        out.append({"tilt_deg": tilt, "rays": int(d.size), "median_deflection_deg": float(np.median(d)),
                    "share_above_1_deg": float(np.mean(d > 1.0))})
    return out


class _LoadTimer:
    """Times ChunkCache.require (reading and bit-packing chunks) inside trace_in_voxels."""

    def __init__(self):
        self.seconds = 0.0
        self._require = ChunkCache.require

    def __enter__(self):
        def timed(cache, *a, **k):
            t0 = time.perf_counter()
            try:
                return self._require(cache, *a, **k)
            finally:
                self.seconds += time.perf_counter() - t0
        ChunkCache.require = timed
        return self

    def __exit__(self, *exc):
        ChunkCache.require = self._require


def birch_speed(block, rays: dict, repeats: int = 5) -> dict:
    """Each preset's speed on ``block``, best of ``repeats`` runs taken in turn
    (paper, fast, accurate, paper, ...), so that a slow spell of the shared
    machine does not fall on one preset only.

    ``rays``: name -> (preset, rays, polymer index); the wall's is 1.50.  A run
    with the polymer at 1.50 too meets its interfaces without a normal: the
    traversal and chunk reading alone, what a free normal estimator would cost.
    """
    src = ArraySource(block, chunks=(128, 128, 128))
    best = {name: (math.inf, 0.0, None) for name in rays}
    for m, _, n_poly in rays.values():
        trace_in_voxels(src, square_beam(2, 10.0, (100, 100), seed=1), n_wall=1.50, n_poly=n_poly,
                   settings=settings_for(m))  # compile
    for _ in range(repeats):
        for name, (m, n, n_poly) in rays.items():
            beam = square_beam(n, 150.0 / 0.5, (block.shape[0] / 2, block.shape[2] / 2), seed=3)
            with _LoadTimer() as timer:
                t0 = time.perf_counter()
                res = trace_in_voxels(src, beam, n_wall=1.50, n_poly=n_poly, settings=settings_for(m))
                t = time.perf_counter() - t0
            if t < best[name][0]:
                best[name] = (t, timer.seconds, res)
    out = {}
    for name, (dt, loading, res) in best.items():
        s = summarize(res, n_boot=50)
        n_if = float(res.events.sum())
        out[name] = {
            "rays": rays[name][1],
            "delta_ri": round(1.50 - rays[name][2], 6),
            "seconds": dt,
            "seconds_loading_chunks": loading,
            "rays_per_s": rays[name][1] / dt,
            "interfaces_per_s": n_if / dt,
            "us_per_interface": 1e6 * dt / n_if,
            # The same without reading and bit-packing the block's chunks (the
            # same work for every method: 36 chunks of 128³ for 1000 rays here).
            "us_per_interface_chunks_resident": 1e6 * (dt - loading) / n_if,
            "fwhm_r_deg": s["fwhm_r_deg"],
            "fwhm_l_deg": s["fwhm_l_deg"],
            "haze": s["haze"],
        }
    return out


@njit(nogil=True)
def _window_normals(bits, masks, table, box, cs, shape, X, D, s, out, wts, segs, slots):
    """surface_normal of settings ``s`` = (sigma, radius, newton, refit) at each point X[r]."""
    nrm = np.empty(3)
    for r in range(X.shape[0]):
        _normals.surface_normal(bits, masks, table, box, cs, shape, X[r], D[r], s[0], s[1], np.int64(s[2]),
                         np.int64(s[3]), nrm, wts, segs, slots)
        out[r] = nrm


def normal_estimators(block, n_svm: int = 300, n_window: int = 100_000, seed: int = 0) -> dict:
    """Each estimator's cost per normal on the same birch interface points: voxel faces
    between the two phases, mostly T faces crossed by rays near +T, as in the beam."""
    rng = np.random.default_rng(seed)
    X, D = [], []
    while len(X) < n_window:
        i, j, k = rng.integers(16, np.asarray(block.shape) - 17)
        ax = 1 if rng.random() < 0.7 else int(rng.integers(0, 3))
        e = np.eye(3, dtype=np.int64)[ax]
        if block[i, j, k] != block[i + e[0], j + e[1], k + e[2]]:
            x = np.array([i, j, k]) + rng.random(3)
            x[ax] = (i, j, k)[ax] + 1.0
            d = rng.normal(0.0, 0.2, 3)
            d[ax] = 1.0
            X.append(x)
            D.append(d / np.linalg.norm(d))
    X, D = np.array(X), np.array(D)
    src = ArraySource(block, chunks=(128, 128, 128))
    cache = ChunkCache(src, capacity=64)
    cache.require(np.ndindex(*(-(-n // c) for n, c in zip(block.shape, src.chunks))))
    view = (cache.bits, cache.masks, cache.table, cache.box, cache.chunk_shape,
            np.asarray(block.shape, np.int64))
    out = {"points": n_window, "svm_points": n_svm}
    box = settings_for("paper").voxel.svm_box

    def paper_normal(x):  # the box around x as the tracer reads it
        lo = np.floor(x).astype(np.int64) - (box // 2 - 1)
        return svm_normal(cache.voxels(lo, (box,) * 3), x, lo)

    paper_normal(X[0])  # imports scikit-learn
    t0 = time.perf_counter()
    for x in X[:n_svm]:
        paper_normal(x)
    out["paper_us"] = 1e6 * (time.perf_counter() - t0) / n_svm
    for m in ("fast", "accurate"):
        st = settings_for(m).voxel
        s = np.array([st.sigma_vox, st.radius_vox, st.newton, st.refit], np.float64)
        scratch = _normals.window_scratch(st.radius_vox)
        normals = np.empty_like(X)
        _window_normals(*view, X[:10], D[:10], s, normals[:10], *scratch)  # compile
        best = math.inf
        for _ in range(3):
            t0 = time.perf_counter()
            _window_normals(*view, X, D, s, normals, *scratch)
            best = min(best, time.perf_counter() - t0)
        out[f"{m}_us"] = 1e6 * best / n_window
        out[f"speedup_{m}"] = out["paper_us"] / out[f"{m}_us"]
    cache.release()
    return out


def lazy_trace(thickness_mm=1.5, rays=1000, chunks=(64, 64, 64), threads=1) -> dict:
    from pipeline.optics import sources

    sources._PACKED.clear()  # cold: nothing packed by an earlier trace of this process
    p = build_params("birch")
    src = WoodSource(p, thickness_um=thickness_mm * 1000, seed=1, chunks=chunks, threads=threads)
    t0 = time.perf_counter()
    res = trace_in_voxels(src, square_beam(rays, 300.0, seed=1), n_wall=1.50, n_poly=1.49,
                     settings=settings_for("accurate"), capacity=2048)
    dt = time.perf_counter() - t0
    s = summarize(res, n_boot=100)
    whole = (3000 / chunks[0]) * (thickness_mm * 2000 / chunks[1]) * (2000 / chunks[2])
    return {
        "thickness_mm": thickness_mm, "rays": rays, "method": "accurate", "seconds": dt, "threads": threads,
        "voxels_generated": len(src.distinct) * int(np.prod(chunks)), "voxels_read": s["voxels_read"],
        "chunks_generated": src.generated, "distinct_chunks": len(src.distinct),
        "chunk_shape": list(chunks),
        "chunks_of_whole_sample_1.5x1.5x1mm": int(np.ceil(whole)),
        "fraction_of_whole_sample": len(src.distinct) / whole,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "fwhm_r_deg": s["fwhm_r_deg"], "fwhm_l_deg": s["fwhm_l_deg"], "haze": s["haze"],
        "n_transmitted": s["n_transmitted"], "counts": s["counts"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/bench.json")
    ap.add_argument("--lazy-only", action="store_true", help="only the lazy 1.5 mm traces (into the existing section)")
    args = ap.parse_args()
    if args.lazy_only:
        import json
        from pathlib import Path

        doc = json.loads(Path(args.out).read_text())
        write_section(args.out, "trace", {**doc.get("trace", {}), **lazy_sections()})
        return
    p = build_params("birch")
    g = make_grid((200.0, 250.0, 200.0), 0.5, (0.0, 0.0, 0.0), p)
    block = generate_block(p, g, (0, 0, 0), g.shape, seed=2)
    res = {
        "rods_R30": {"paper": rod_errors("paper", 60), "fast": rod_errors("fast", 500),
                     "accurate": rod_errors("accurate", 500)},
        "tubes_R30": {m: [tube_errors(m, w) for w in (1.0, 1.5, 2.0, 3.0, 4.0, 6.0)]
                      for m in ("fast", "accurate")},
        "sheets": {m: {"wall_1_voxel": sheet_errors(m, 1.0), "polymer_1_voxel": sheet_errors(m, 1.0, phase=0),
                       "wall_2_voxels": sheet_errors(m, 2.0)} for m in ("fast", "accurate")},
        "birch_0_25mm": birch_speed(block, {"paper": ("paper", 20, 1.49), "fast": ("fast", 1000, 1.49),
                                            "accurate": ("accurate", 1000, 1.49),
                                            "index_matched": ("fast", 1000, 1.50)}),
    }
    b = res["birch_0_25mm"]
    # index_matched: the most any estimator could reach over paper on this
    # block, its normals being free and the traversal and reading as they are.
    others = ("fast", "accurate", "index_matched")
    res["speedup_per_interface_over_paper"] = {
        m: b["paper"]["us_per_interface"] / b[m]["us_per_interface"] for m in others}
    res["speedup_per_interface_over_paper_chunks_resident"] = {
        m: b["paper"]["us_per_interface_chunks_resident"] / b[m]["us_per_interface_chunks_resident"]
        for m in others}
    res["normal_estimators"] = normal_estimators(block)
    res.update(lazy_sections())
    write_section(args.out, "trace", res)


def lazy_sections() -> dict:
    return {"lazy_1_5mm": lazy_trace(),
            "lazy_1_5mm_2_threads": lazy_trace(threads=2)}  # as `twray trace` generates on 2 cores


if __name__ == "__main__":
    main()
