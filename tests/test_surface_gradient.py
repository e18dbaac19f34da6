"""The analytic gradient of each primitive of the wood's surfaces against central differences of the
model itself (docs/methods.md#analytic-normals)."""

import math

import numpy as np
import pytest

from pipeline.microstructure import region as R
from pipeline.microstructure.surface import (MAX_PRIMS, N_COLS, P_BAND, P_FACE, P_LUMEN, P_PLATE, P_PLY, P_RAY_END,
                                             P_RAY_LUMEN, P_REACH, P_TIP, P_TIP_END, P_VESSEL_IN, P_VESSEL_OUT,
                                             P_VESSEL_SHARED, evaluate_at, new_cache)
from pipeline.microstructure.surface_gradient import gradient_at
from pipeline.params import build_params

H = 1e-4  # [µm] the differences' step: truncation ~H²·g''' and rounding ~1e-16·|X|/H, both < 1e-8
PER_KIND = 150  # rows checked per kind and variant

# (preset, overrides, thickness [µm], half-width along L [µm], kinds that must be checked)
CASES = {
    "birch": ("birch", {}, 400.0, 200.0,
              {P_BAND, P_RAY_LUMEN, P_RAY_END, P_VESSEL_OUT, P_VESSEL_IN, P_VESSEL_SHARED, P_LUMEN, P_PLATE}),
    "birch with fibre tips": ("birch", {"fibre_tip_um": 200.0}, 80.0, 60.0, {P_TIP, P_TIP_END, P_LUMEN}),
    "laminate [0/45/90/-30]": ("birch", {"laminate": (0, 45, 90, -30), "ply_thickness_um": 20.0}, 80.0, 30.0,
                               {P_PLY, P_LUMEN, P_VESSEL_OUT, P_BAND}),
    "balsa": ("balsa", {}, 80.0, 30.0, {P_FACE, P_PLATE}),
}


def _g(x, key, ctx, Q, cache):
    _, m = evaluate_at(x[0], x[1], x[2], 0.0, ctx, Q, cache, key)
    for i in range(m):
        if np.array_equal(Q[i, :5], key):
            return Q[i, 5]
    return np.nan


def _near_grid_line(x, ctx, G):
    """Whether a difference of step H could straddle a line of some ply's bilinear pull-back grid
    (where the gradient is one-sided and central differences average the two sides)."""
    for cs, sn, oR, oT, _ in ctx[2]:
        for v in (cs * x[0] + sn * x[2] + oR, x[1] + oT):
            if abs(v / G - round(v / G)) * G < 2.0 * H:
                return True
    return False


@pytest.mark.parametrize("case", list(CASES))
def test_the_analytic_gradient_of_every_primitive_is_its_central_difference(case):
    """At random points of each wood kind, every primitive listed there (fibre and vessel lumens,
    shared vessel walls, ray bands, ray-cell lumens and ends, end plates, tip walls and their ends,
    balsa's faces, plies) has an analytic gradient, in space, through the ply's rotation, the
    pull-back, the squeeze and the geometry's motion along L; it equals the central differences of
    that primitive's g to their own error (relative 1e-6; they agree to about 1e-9)."""
    preset, changes, thickness, half_l, kinds = CASES[case]
    p = build_params(preset, overrides=changes)
    ctx = R.context_tuple(R.region_context(p, 2, thickness, (-30.0, 30.0), (-half_l, half_l)))
    G = p.node_pitch_um / 8.0
    rng = np.random.default_rng(11)
    P = np.empty((MAX_PRIMS, N_COLS))
    Q = np.empty((MAX_PRIMS, N_COLS))
    cache = new_cache()
    out = np.zeros(3)
    checked = {}
    worst = 0.0
    for _ in range(6000):
        x = np.array([rng.uniform(-25.0, 25.0), rng.uniform(1.0, thickness - 1.0),
                      rng.uniform(-half_l + 5.0, half_l - 5.0)])
        if _near_grid_line(x, ctx, G):
            continue
        _, n = evaluate_at(x[0], x[1], x[2], 0.0, ctx, P, cache, np.zeros(5))
        for row in P[:n].copy():
            kind = int(row[0])
            if kind == P_REACH or row[6] > 1e200 or checked.get(kind, 0) >= PER_KIND:
                continue  # the reach row is no surface; an infinite clearance: no crossing here
            key = row[:5].copy()
            assert gradient_at(x[0], x[1], x[2], ctx, key, cache, out), (kind, x)
            fd = np.empty(3)
            for q in range(3):
                e = np.zeros(3)
                e[q] = H
                fd[q] = (_g(x + e, key, ctx, Q, cache) - _g(x - e, key, ctx, Q, cache)) / (2.0 * H)
            err = np.abs(out - fd).max() / np.abs(fd).max()
            worst = max(worst, err)
            assert err < 1e-6, (kind, x, out, fd)
            checked[kind] = checked.get(kind, 0) + 1
        if all(checked.get(k, 0) >= PER_KIND for k in kinds):
            break
    assert kinds <= set(checked), (kinds - set(checked), checked)
    assert all(math.isfinite(v) for v in out)
    assert worst < 1e-6
