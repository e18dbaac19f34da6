"""One point of a surface medium for the exact march (docs/methods.md#the-exact-method): its phase
and rows, and the normal of one of its primitives, for generated wood or a reference lattice,
chosen by the context's type when the march compiles, so that one kernel traces both."""

from numba import types
from numba.extending import overload

from ..microstructure.surface import evaluate_at
from ..microstructure.surface_gradient import gradient_at
from ..microstructure.surface_ray import along_clearances, lumen_root
from ._lattice_rows import CONTEXT_LEN, lattice_normal, lattice_rows


def _is_lattice(ctx) -> bool:
    return isinstance(ctx, types.BaseTuple) and len(ctx) == CONTEXT_LEN


def surface_at(R, T, L, lq, ctx, P, cache, want):
    """(phase, number of rows) of the medium of ``ctx`` at (R, T, L), its rows in ``P``: generated
    wood (:func:`~pipeline.microstructure.surface.evaluate_at`) or a reference lattice
    (:func:`~pipeline.optics._lattice_rows.lattice_rows`).  Chosen by the context's type when the
    march compiles, so one kernel traces both."""
    raise NotImplementedError("surface_at runs inside the march's Numba kernel only")


@overload(surface_at, inline="always")
def _surface_at(R, T, L, lq, ctx, P, cache, want):
    if _is_lattice(ctx):
        return lambda R, T, L, lq, ctx, P, cache, want: lattice_rows(R, T, ctx, P)
    return lambda R, T, L, lq, ctx, P, cache, want: evaluate_at(R, T, L, lq, ctx, P, cache, want)


def surface_normal(base, lq, ctx, P, key, cache, nrm):
    """(found, evaluations): the normal of primitive ``key`` at ``base`` into ``nrm`` (not yet of
    unit length).  The wood's is the analytic gradient of its g
    (:func:`~pipeline.microstructure.surface_gradient.gradient_at`, one evaluation of that
    primitive); a lattice's, its circle's or face's own."""
    raise NotImplementedError("surface_normal runs inside the march's Numba kernel only")


@overload(surface_normal)
def _surface_normal(base, lq, ctx, P, key, cache, nrm):
    if _is_lattice(ctx):
        return lambda base, lq, ctx, P, key, cache, nrm: (lattice_normal(base[0], base[1], ctx, key, nrm), 0)
    return lambda base, lq, ctx, P, key, cache, nrm: (gradient_at(base[0], base[1], base[2], ctx, key, cache, nrm), 1)


def ray_clearances(R, T, L, d, ctx, P, n, F, skip):
    """Raise the clearances of the rows P[:n] at (R, T, L) (``skip``: the row crossed last, or -1) to
    proven steps along ``d`` where the medium has them: the wood's fibre lumens
    (:func:`~pipeline.microstructure.surface_ray.along_clearances`); a lattice's balls stay."""
    raise NotImplementedError("ray_clearances runs inside the march's Numba kernel only")


@overload(ray_clearances, inline="always")
def _ray_clearances(R, T, L, d, ctx, P, n, F, skip):
    if _is_lattice(ctx):
        return lambda R, T, L, d, ctx, P, n, F, skip: None
    return lambda R, T, L, d, ctx, P, n, F, skip: along_clearances(R, T, L, d, ctx, P, n, F, skip)


def root_guess(F, P, i, ctx):
    """A guess at the distance along the ray to row i's root from the frame F (wood lumens,
    :func:`~pipeline.microstructure.surface_ray.lumen_root`); -1 for none."""
    raise NotImplementedError("root_guess runs inside the march's Numba kernel only")


@overload(root_guess, inline="always")
def _root_guess(F, P, i, ctx):
    if _is_lattice(ctx):
        return lambda F, P, i, ctx: -1.0
    return lambda F, P, i, ctx: lumen_root(F, P, i)
