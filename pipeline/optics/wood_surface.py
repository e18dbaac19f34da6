"""Generated wood as a surface medium: the method ``exact`` traces the model's own surfaces,
no voxels (docs/methods.md#the-exact-method).

The phase at a point is the generator's, bit for bit
(:mod:`pipeline.microstructure.surface`); the tracer steps by proven
clearances and bisects each crossing (:mod:`pipeline.optics._surface_march`).
What a region of wood needs (distortion tiles, vessels) is built for the box
around the entry points; a ray that leaves it goes on from the start of its
last straight segment, with the state it had there, in a small region ahead
of it, so the result does not depend on the regions.
"""

from __future__ import annotations

import collections
import json
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..microstructure.region import context_tuple, phases, region_context, warm_regions
from ..microstructure.surface import new_cache
from ..params import WoodParams
from ._surface_march import BOUNDS, COUNTS, HIT, NEEDS_REGION, PURPOSES, STEP_BOUNDS, TOL, march, new_work
from .interface import SIDE

# Internal steps [µm] (docs/methods.md#the-exact-method); halving them leaves the rays as they are
# (crossings land on a fixed lattice).
STEP_SCALE = 1.0  # fraction of the clearance stepped (1: the whole proven clearance)
# Steps proven along the ray (pipeline/microstructure/surface_ray.py), not the rows' balls alone
# (`exact` 5; False is `exact` 4's march, kept for comparison: docs/performance.md).
ALONG = True
NAMES = ("position", "direction", "status", "events", "path", "evaluations", "passes", "medium")
FIRST_MARGIN_UM = 40.0  # region around the entry points, plus 5 % of the thickness (the base margin)
AHEAD_MAX = 8.0  # a ray that leaves a region goes on in one reaching 2, 4, then at most 8 base margins ahead
MAX_ROUNDS = 10_000  # regions a beam may need before its rays count as lost (each goes 2-8 base margins further)
_SHARED = threading.Lock()  # the region count, the evaluation counts and the free memos
# Memos and work buffers free for the next slice of any trace in this process, per wood parameters
# (no more lists than MEMO_PARAMS, no more memos in one than the slices that ran at once).  A memo
# holds functions of the parameters and of ids (a node's control values, a fibre's cell, a ray
# group's span, each keyed by its seed too) and changes no result, only what it costs: a study's
# next shard of the same parameters starts with what the last one's rays warmed, not a cold 3 MB memo.
_MEMOS: collections.OrderedDict = collections.OrderedDict()
MEMO_PARAMS = 4
SLICES, SLICE_RAYS = 4, 16  # a group's rays in up to 4 slices a thread, of at least 16 rays


class WoodSurface:
    """Generated wood of ``params`` and ``seed`` between T = 0 and T = ``thickness_um`` [µm],
    unbounded along R and L, as a surface medium (method ``exact``)."""

    def __init__(self, params: WoodParams, *, thickness_um: float, seed: int = 1, threads: int = 1,
                 hit: float = HIT, tol: float = TOL, step_scale: float = STEP_SCALE, along: bool | None = None,
                 margin_um: float | None = None, r_bounds_um: tuple | None = None):
        self.params = params
        # A wood bounded along R (a window of a section): a ray that ends outside, or whose next region
        # would start or reach outside, leaves through a side (status SIDE), so that no ray wanders far
        # along R; one that crosses a bound and comes back within one region is not caught (a bound
        # against wandering, not an exact wall).  None: unbounded.
        self.r_bounds_um = None if r_bounds_um is None else (float(r_bounds_um[0]), float(r_bounds_um[1]))
        self.thickness_um = float(thickness_um)
        self.seed = int(seed)
        self.hit, self.tol, self.step_scale = float(hit), float(tol), float(step_scale)
        self.along = ALONG if along is None else bool(along)
        self.token = ("wood-surfaces", json.dumps(params.to_dict(), sort_keys=True), self.seed, self.thickness_um)
        # The base margin of regions [µm]; it changes how many are built, never a ray's numbers.
        self.margin_um = FIRST_MARGIN_UM + 0.05 * self.thickness_um if margin_um is None else float(margin_um)
        self.left = 0  # times a ray left its region and went on in another
        self.regions = 0  # region contexts built (each widening counts)
        # point evaluations of the traces so far, by what each was for (_surface_march.PURPOSES)
        self.evaluations = dict.fromkeys(PURPOSES, 0)
        self.steps = dict.fromkeys(STEP_BOUNDS, 0)  # their steps, by what bounded each (STEP_BOUNDS)
        self.threads = max(1, int(threads))  # slices of a beam traced side by side

    @staticmethod
    def _bounds(pos: np.ndarray, margin: float) -> tuple:
        """(R range, L range, None: the whole thickness) of the box around ``pos`` widened by ``margin``."""
        r = (float(np.min(pos[:, 0])) - margin, float(np.max(pos[:, 0])) + margin)
        l = (float(np.min(pos[:, 2])) - margin, float(np.max(pos[:, 2])) + margin)
        return r, l, None

    def _context(self, pos: np.ndarray, margin: float) -> tuple:
        return self._box(*self._bounds(pos, margin))

    def _box(self, r: tuple, l: tuple, t: tuple | None = None) -> tuple:
        with _SHARED:  # regions of a round are built on several threads
            self.regions += 1
        return context_tuple(region_context(self.params, self.seed, self.thickness_um, r, l, t, threads=self.threads))

    def _regions(self, todo, start, stop, heading, ahead, base) -> list:
        """Regions for the rays ``todo`` that left theirs: rays that stopped in one cube of 4·``base``
        [µm] share one, the box around their last segments (start to stop) widened by ``base``, and
        along each ray's heading by ``ahead`` more (in proportion on the axes it moves less along),
        within the sample's thickness."""
        if not todo.size:
            return []
        a, b, h = start[todo], stop[todo], heading[todo]
        # ahead along the heading's largest component, in proportion along the others
        far = ahead[todo] / np.maximum(np.abs(h).max(axis=1), 1e-300)
        box = []
        for axis in range(3):
            lo = np.minimum(a[:, axis], b[:, axis]) - base - np.where(h[:, axis] < 0.0, -h[:, axis] * far, 0.0)
            hi = np.maximum(a[:, axis], b[:, axis]) + base + np.where(h[:, axis] > 0.0, h[:, axis] * far, 0.0)
            box.append((lo, hi))
        cells = np.floor(b / (4.0 * base)).astype(np.int64)
        _, which = np.unique(cells, axis=0, return_inverse=True)
        which = which.reshape(-1)
        groups = []
        for g in range(which.max() + 1):
            m = which == g
            r, t, l = ((float(lo[m].min()), float(hi[m].max())) for lo, hi in box)
            groups.append((todo[m], (r, l, (max(t[0], 0.0), min(t[1], self.thickness_um)))))
        return groups

    def _round(self, groups, start, heading, ids, out, skips, stop, log, resume, log_events, optics) -> list:
        """Trace each group (rays, region box) of a round in its region; the rays of each that left it.

        Rays are independent and a ray's numbers do not depend on its region, so the work is cut
        as the threads are best used: a lone group's rays in slices side by side (its region's
        tiles computed on the threads first); several groups (the rays that left the regions
        before) with all their regions' tiles computed at once, then their slices, largest
        groups first, on the threads, each region built by the first slice that needs it and let
        go after its last.  Slices of SLICE_RAYS or more rays, several a thread, so that threads
        finish together; a slice takes a memo and work buffers from :data:`_MEMOS` (those of slices
        done before, on any thread, in any trace) and gives them back with its evaluations counted
        (a memo changes no result, only what it costs)."""
        if len(groups) > 1:
            warm_regions(self.params, self.seed, self.thickness_um, [box for _, box in groups], self.threads)
        work = []  # per group: rays, box, result arrays, [context, slices left], lock
        jobs = []
        for todo, box in sorted(groups, key=lambda g: -g[0].size):
            k = todo.size
            res = [out[name][todo] for name in NAMES] + [skips[todo], stop[todo], log[todo] if log_events else log]
            cuts = np.linspace(0, k, min(SLICES * self.threads, max(1, k // SLICE_RAYS)) + 1).astype(int)
            work.append((todo, box, res, [None, len(cuts) - 1], threading.Lock()))
            jobs += [(len(work) - 1, lo, hi) for lo, hi in zip(cuts[:-1], cuts[1:])]
        if len(work) == 1:  # the lone region's tiles on the threads, before its slices
            work[0][3][0] = self._box(*work[0][1])

        def run(job):
            todo, box, res, held, lock = work[job[0]]
            lo, hi = job[1], job[2]
            with lock:
                if held[0] is None:
                    held[0] = self._box(*box)
                ctx = held[0]
            sel = todo[lo:hi]
            with _SHARED:
                free = _MEMOS.setdefault(self.token[1], [])
                _MEMOS.move_to_end(self.token[1])
                while len(_MEMOS) > MEMO_PARAMS:
                    _MEMOS.popitem(last=False)
                memo = free.pop() if free else (new_cache(), new_work())
            march(start[sel], heading[sel], ids[sel], self.thickness_um, *optics, ctx,
                  self.hit, self.tol, self.step_scale, self.along, *(a[lo:hi] for a in res[:8]),
                  res[10][lo:hi] if log_events else res[10], memo[0], resume[sel],
                  res[8][lo:hi], res[9][lo:hi], memo[1])
            with _SHARED:
                for name, v in zip(PURPOSES, memo[1][COUNTS:BOUNDS]):
                    self.evaluations[name] += int(v)
                for name, v in zip(STEP_BOUNDS, memo[1][BOUNDS:]):
                    self.steps[name] += int(v)
                memo[1][COUNTS:] = 0.0
                free.append(memo)  # for the next slice on any thread: no more memos than threads
            with lock:
                held[1] -= 1
                if held[1] == 0:
                    held[0] = None  # its last slice: the region is let go

        if self.threads > 1 and len(jobs) > 1:
            with ThreadPoolExecutor(min(self.threads, len(jobs))) as pool:
                list(pool.map(run, jobs))  # the kernel releases the GIL
        else:
            for job in jobs:
                run(job)
        left = []
        for todo, _, res, _, _ in work:
            for name, arr in zip(NAMES, res):
                out[name][todo] = arr
            skips[todo], stop[todo] = res[8], res[9]
            if log_events:
                log[todo] = res[10]
            left.append(todo[res[2] == NEEDS_REGION])
        return left

    def entry_phase(self, origins_um: np.ndarray) -> np.ndarray:
        """The phase (1 wall, 0 polymer) at each entry point (T taken as 0)."""
        pos = np.array(origins_um, np.float64, copy=True).reshape(-1, 3)
        pos[:, 1] = 0.0
        return phases(pos, 0.0, self._context(pos, 1.0))

    def march_walls(self, origins_um, directions, *, n_wall: float, n_poly: float, max_events: int,
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
        base = self.margin_um
        log = np.zeros((n, log_events, 12) if log_events else (0, 0, 12))
        resume = np.zeros(n, np.uint8)
        skips = np.zeros((n, 5))
        stop = np.empty((n, 3))
        start, heading = pos0.copy(), dirs0.copy()  # where each ray (re)starts: its last segment
        ahead = np.full(n, base)  # how far a ray's next region reaches along its heading
        groups = [(np.arange(n), self._bounds(pos0, base))]
        rounds = 0
        while groups:
            left = self._round(groups, start, heading, ids, out, skips, stop, log, resume, log_events,
                               (float(n_wall), float(n_poly), int(max_events), bool(fresnel), np.uint64(seed)))
            todo = np.concatenate(left)
            if self.r_bounds_um is not None and todo.size:
                lo, hi = self.r_bounds_um
                r = np.stack([out["position"][todo, 0], stop[todo, 0]])
                gone = np.any((r < lo) | (r > hi), axis=0)
                out["status"][todo[gone]] = SIDE
                todo = todo[~gone]
            # A ray that left goes on from its last segment's start, in a region around that
            # segment reaching twice as far ahead as the last one did.
            start[todo] = out["position"][todo]
            heading[todo] = out["direction"][todo]
            resume[todo] = 1
            self.left += todo.size
            groups = self._regions(todo, start, stop, heading, ahead, base)
            ahead[todo] = np.minimum(2.0 * ahead[todo], AHEAD_MAX * base)
            rounds += 1
            if rounds > MAX_ROUNDS:
                raise RuntimeError("rays left every region tried: the tracer lost them")
        if self.r_bounds_um is not None:
            lo, hi = self.r_bounds_um
            out["status"][(out["position"][:, 0] < lo) | (out["position"][:, 0] > hi)] = SIDE
        if log_events:
            out["log"] = log
        return out


