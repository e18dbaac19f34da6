"""Proven steps along a ray (pipeline/microstructure/surface_ray.py, docs/methods.md#proven-steps-along-the-ray):
no primitive whose clearance they raise switches within it, and no lumen left unlisted is met
within the fibre cells' reach, checked against the model's own g sampled along each step."""

import math

import numpy as np
import pytest

from pipeline.microstructure import region as R
from pipeline.microstructure.surface import (MAX_PRIMS, N_COLS, P_BAND, P_FACE, P_LUMEN, P_PLATE, P_PLY,
                                             P_RAY_LUMEN, P_REACH, P_TIP_END, evaluate_at, find_row, new_cache)
from pipeline.microstructure.surface_ray import N_FRAME, along_clearances
from pipeline.params import build_params

CASES = {
    "birch": ("birch", {}),
    "birch, fibre tips": ("birch", {"fibre_tip_um": 150.0}),
    "laminate [0/50/-35]": ("birch", {"laminate": (0, 50, -35), "ply_thickness_um": 40.0}),
    "balsa": ("balsa", {}),
}
SAMPLES = 200  # points along each raised step, and as many again in its last hundredth


def _directions(rng, k):
    """Mostly along T, as a sheet is lit, out to 75° off it, either way."""
    th = np.radians(rng.uniform(0.0, 75.0, k))
    ph = rng.uniform(0.0, 2.0 * math.pi, k)
    d = np.column_stack([np.sin(th) * np.cos(ph), np.cos(th), np.sin(th) * np.sin(ph)])
    return d * np.where(rng.uniform(size=k) < 0.2, -1.0, 1.0)[:, None]


def _along(s_max):
    return np.concatenate([np.linspace(0.0, s_max, SAMPLES), s_max * (1.0 - np.linspace(0.0, 0.01, SAMPLES))])


@pytest.mark.parametrize("case", list(CASES))
def test_no_primitive_switches_within_its_proven_step(case):
    """At random points and directions, the generator's phase does not change within the least
    raised clearance; every fibre lumen, ray-cell lumen, ray band, balsa face and end plate whose
    clearance the ray's frame raised keeps the sign of its g over the whole step (the model's own
    g, sampled along it); and within the raised reach rows, every lumen (band, balsa centre) met
    was listed at the start.  The steps are worth proving: a lumen's step is longer than the
    ball they replace (median 1.7 times in birch)."""
    preset, changes = CASES[case]
    p = build_params(preset, overrides=changes)
    thickness = 240.0
    ctx = R.context_tuple(R.region_context(p, 3, thickness, (-60.0, 60.0), (-60.0, 60.0)))
    rng = np.random.default_rng(17)
    P = np.empty((MAX_PRIMS, N_COLS))
    Q = np.empty((MAX_PRIMS, N_COLS))
    F = np.empty(N_FRAME)
    cache = new_cache()
    raised = {P_LUMEN: [], P_RAY_LUMEN: [], P_BAND: [], P_REACH: [], P_FACE: [], P_PLATE: [], P_TIP_END: []}
    checked = [0, 0]  # samples checked, and those where the row was not listed
    steps = []
    k = 3000  # the march's step at every point; each raised row's own at the first 300
    for x, d in zip(np.column_stack([rng.uniform(-40, 40, k), rng.uniform(40, 200, k), rng.uniform(-40, 40, k)]),
                    _directions(rng, k)):
        _, n = evaluate_at(x[0], x[1], x[2], 0.0, ctx, P, cache, np.zeros(5))
        balls = P[:n, 6].copy()
        along_clearances(x[0], x[1], x[2], d, ctx, P, n, F, -1)
        rows = P[:n].copy()
        # The march's step (docs/methods.md#the-exact-method): A the row of least clearance, the
        # others' least clearance beside it; outside A no phase change within A's clearance, inside
        # A (convex) at most one within the others'.
        order = np.argsort(rows[:, 6])
        a = next((k for k in order if rows[k, 0] != P_REACH), None)
        if a is not None:
            other = min(rows[k, 6] for k in range(n) if k != a)
            inside = rows[a, 5] < 0.0 and rows[a, 0] not in (P_BAND, P_PLY)
            step = other if inside else min(rows[a, 6], other)
            if step < 1e300:
                ph = R.phases(x + _along(step)[np.argsort(_along(step))][:, None] * d, 0.0, ctx)
                assert np.count_nonzero(np.diff(ph.astype(int))) <= (1 if inside else 0), (case, x, d, step)
                steps.append(step)
        if len(steps) > 200:
            continue
        # A ply boundary bounds every step (a regime surface, never stepped over blindly): beyond it
        # another ply's rows apply.
        ply = min([r[6] for r in rows if r[0] == P_PLY], default=1e300)
        for row, ball in zip(rows, balls):
            kind = int(row[0])
            if kind not in raised or row[6] <= ball:
                continue
            raised[kind].append(row[6] / ball)
            key = row[:5].copy()
            for s in _along(min(row[6], ply)):
                y = x + s * d
                if kind == P_REACH:  # no lumen (band, balsa centre) met but those listed at the start
                    _, m = evaluate_at(y[0], y[1], y[2], 0.0, ctx, Q, cache, np.zeros(5))
                    for q in range(m):
                        if row[1] == 2.0 and Q[q, 0] == P_FACE:  # the nearest centre there
                            assert any(r[0] == P_FACE and (tuple(r[1:3]) == tuple(Q[q, 1:3])
                                                           or tuple(r[3:5]) == tuple(Q[q, 1:3])) for r in rows), \
                                (case, x, d, s)
                        elif Q[q, 0] == (P_LUMEN if row[1] == 1.0 else P_BAND) and Q[q, 5] <= 0.0:
                            assert find_row(rows, n, Q[q, :5]) >= 0, (case, x, d, s)
                    checked[0] += 1
                    continue
                _, m = evaluate_at(y[0], y[1], y[2], 0.0, ctx, Q, cache, key if kind in (P_LUMEN, P_RAY_LUMEN)
                                   else np.zeros(5))
                j = find_row(Q, m, key)
                if j < 0:  # into a ray band (no fibre lumens there) or out of it (no ray cells)
                    checked[1] += 1
                    continue
                checked[0] += 1
                assert (Q[j, 5] > 0.0) == (row[5] > 0.0), (case, kind, x, d, s, row[6], Q[j, 5])
    assert checked[1] < 0.1 * checked[0] and len(steps) > 2500
    assert len(raised[P_BAND]) > 20 and len(raised[P_REACH]) > 120
    if preset == "balsa":
        assert len(raised[P_FACE]) > 200 and np.median(raised[P_FACE]) > 1.4
        return
    assert len(raised[P_LUMEN]) > 120 and np.median(raised[P_LUMEN]) > 1.4
    if case == "birch":
        assert len(raised[P_RAY_LUMEN]) > 10
