"""Generated wood as a surface medium: the method ``exact`` traces the model's own surfaces,
no voxels (docs/methods.md#the-exact-method).

The phase at a point is the generator's, bit for bit
(:mod:`pipeline.microstructure.surface`); the tracer steps by proven
clearances and bisects each crossing (:mod:`pipeline.optics._surface_march`).
What a region of wood needs (distortion tiles, vessels) is built for the box
around the entry points; a ray that leaves it is traced again, from its start,
in a box around its path so far and wider, so the result does not depend on
the box.
"""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..microstructure.region import context_tuple, phases, region_context
from ..microstructure.surface import new_cache
from ..params import WoodParams
from ._surface_march import HIT, NEEDS_REGION, TOL, march

# Internal steps [µm] (docs/methods.md#the-exact-method); halving them leaves the rays as they are
# (crossings land on a fixed lattice).  H_GRAD is part of the normal's definition.
H_GRAD = 1e-6  # central-difference step of a normal
STEP_SCALE = 1.0  # fraction of the clearance stepped (1: the whole proven clearance)
NAMES = ("position", "direction", "status", "events", "path", "evaluations", "passes", "medium")
FIRST_MARGIN_UM = 40.0  # region around the entry points, plus 5 % of the thickness; doubled for rays that leave it


class WoodSurface:
    """Generated wood of ``params`` and ``seed`` between T = 0 and T = ``thickness_um`` [µm],
    unbounded along R and L, as a surface medium (method ``exact``)."""

    def __init__(self, params: WoodParams, *, thickness_um: float, seed: int = 1, threads: int = 1,
                 hit: float = HIT, tol: float = TOL, h_grad: float = H_GRAD, step_scale: float = STEP_SCALE):
        self.params = params
        self.thickness_um = float(thickness_um)
        self.seed = int(seed)
        self.hit, self.tol, self.h_grad, self.step_scale = float(hit), float(tol), float(h_grad), float(step_scale)
        self.token = ("wood-surfaces", json.dumps(params.to_dict(), sort_keys=True), self.seed, self.thickness_um)
        self.regions = 0  # region contexts built (each widening counts)
        self.threads = max(1, int(threads))  # slices of a beam traced side by side

    def _context(self, pos: np.ndarray, margin: float) -> tuple:
        self.regions += 1
        r = (float(np.min(pos[:, 0])) - margin, float(np.max(pos[:, 0])) + margin)
        l = (float(np.min(pos[:, 2])) - margin, float(np.max(pos[:, 2])) + margin)
        return context_tuple(region_context(self.params, self.seed, self.thickness_um, r, l))

    def entry_phase(self, origins_um: np.ndarray) -> np.ndarray:
        """The phase (1 wall, 0 polymer) at each entry point (T taken as 0)."""
        pos = np.array(origins_um, np.float64, copy=True).reshape(-1, 3)
        pos[:, 1] = 0.0
        return phases(pos, 0.0, self._context(pos, 1.0))

    def trace_surfaces(self, origins_um, directions, *, n_wall: float, n_poly: float, max_events: int,
                       fresnel: bool = False, seed: int = 0, ray_ids=None, log_events: int = 0) -> dict:
        pos0 = np.array(origins_um, np.float64, copy=True).reshape(-1, 3)
        pos0[:, 1] = 0.0
        dirs0 = np.ascontiguousarray(directions, np.float64)
        n = len(pos0)
        ids = np.arange(n, dtype=np.int64) if ray_ids is None else np.asarray(ray_ids, np.int64)
        out = {"position": np.empty((n, 3)), "direction": np.empty((n, 3)),
               "status": np.full(n, NEEDS_REGION, np.int64), "events": np.zeros(n, np.int64),
               "path": np.zeros(n), "evaluations": np.zeros(n, np.int64), "passes": np.zeros(n, np.int64),
               "medium": np.zeros(n, np.uint8)}
        margin = FIRST_MARGIN_UM + 0.05 * self.thickness_um
        todo = np.arange(n)
        reached = pos0.copy()  # a ray that leaves a region is traced again in one around its path so far
        while todo.size:
            ctx = self._context(np.concatenate([pos0[todo], reached[todo]]), margin)
            k = todo.size
            res = [np.empty((k, 3)), np.empty((k, 3)), np.empty(k, np.int64), np.empty(k, np.int64),
                   np.empty(k), np.empty(k, np.int64), np.empty(k, np.int64), np.empty(k, np.uint8)]
            log = np.zeros((k, log_events, 12) if log_events else (0, 0, 12))

            def run(lo, hi, pos=pos0[todo], dirs=dirs0[todo], rid=ids[todo], ctx=ctx, res=res, log=log):
                # Rays are independent: slices of the beam run side by side (the kernel releases the GIL).
                march(pos[lo:hi], dirs[lo:hi], rid[lo:hi], self.thickness_um, float(n_wall), float(n_poly),
                      int(max_events), bool(fresnel), np.uint64(seed), ctx, self.hit, self.tol, self.h_grad,
                      self.step_scale, *(a[lo:hi] for a in res), log[lo:hi] if log_events else log, new_cache())

            parts = min(self.threads, max(1, k // 16))
            cuts = np.linspace(0, k, parts + 1).astype(int)
            if parts > 1:
                with ThreadPoolExecutor(parts) as pool:
                    list(pool.map(run, cuts[:-1], cuts[1:]))
            else:
                run(0, k)
            if log_events:
                out.setdefault("log", np.zeros((n, log_events, 12)))[todo] = log
            for name, arr in zip(NAMES, res):
                out[name][todo] = arr
            left = res[2] == NEEDS_REGION
            reached[todo[left]] = res[0][left]
            todo = todo[left]
            margin *= 2.0
            if margin > 1e6:
                raise RuntimeError("rays left every region tried: the tracer lost them")
        return out


