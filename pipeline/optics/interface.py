"""What happens at an interface, for every tracing method: ray statuses, Snell's law,
total internal reflection and Fresnel reflectance (docs/methods.md#refraction-at-an-interface).

Numba kernels and plain constants, so that the voxel kernels, the exact
lattice kernels and the Python around them share one definition.
"""

import math

import numpy as np
from numba import njit

from ..rng import uniform, FRESNEL

# Ray status.
ACTIVE = 0
TRANSMITTED = 1
REFLECTED = 2  # left back through the entrance face
SIDE = 3  # left through a side of a finite volume
TRAPPED = 4  # hit the event cap
NEEDS_CHUNK = 10
NEEDS_NORMAL = 11  # paper mode: waiting for the SVM normal
TIR_EXIT = 5  # transmitted, but totally reflected at the exit face into air (exit: air)

STATUS_NAMES = {TRANSMITTED: "transmitted", REFLECTED: "reflected", SIDE: "side", TRAPPED: "trapped",
                TIR_EXIT: "tir_at_exit_face"}


@njit(inline="always", cache=True, nogil=True)
def refract(d, n, n1, n2, out):
    """Snell refraction or total internal reflection (docs/methods.md#refraction-at-an-interface).

    d : unit incident direction; n : unit normal facing the incoming ray
    (n·d < 0); n1, n2 : indices before and after.  Writes the new direction
    into ``out`` and returns True for total internal reflection.
    """
    if n1 == n2:
        # Index matched: the ray goes straight, exactly.
        for q in range(3):
            out[q] = d[q]
        return False
    cos_i = -(n[0] * d[0] + n[1] * d[1] + n[2] * d[2])
    eta = n1 / n2
    sin2_t = eta * eta * (1.0 - cos_i * cos_i)
    if sin2_t >= 1.0:
        for q in range(3):
            out[q] = d[q] + 2.0 * cos_i * n[q]
        return True
    f = eta * cos_i - math.sqrt(1.0 - sin2_t)
    for q in range(3):
        out[q] = eta * d[q] + f * n[q]
    return False


@njit(inline="always", cache=True, nogil=True)
def fresnel_reflectance(cos_i, n1, n2):
    """Unpolarised Fresnel reflectance; 1 beyond the critical angle."""
    eta = n1 / n2
    sin2_t = eta * eta * (1.0 - cos_i * cos_i)
    if sin2_t >= 1.0:
        return 1.0
    cos_t = math.sqrt(1.0 - sin2_t)
    rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    rp = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t)
    return 0.5 * (rs * rs + rp * rp)


@njit(inline="always", cache=True, nogil=True)
def normalise(v):
    s = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    if s > 0.0:
        v[0] /= s
        v[1] /= s
        v[2] /= s
    return s


@njit(inline="always", cache=True, nogil=True)
def interface_event(d, nrm, medium, n_wall, n_poly, fresnel, seed, ray_id, event, newd):
    """Apply one interface event to unit direction ``d``: the new direction in ``newd``; returns
    the medium (0 polymer, 1 wall) after it.

    ``nrm`` is turned (in place) to face the incoming ray.  With ``fresnel``, a
    refracted ray is reflected instead with the Fresnel reflectance, drawn from
    the stream of (seed, ray_id, event).
    """
    if nrm[0] * d[0] + nrm[1] * d[1] + nrm[2] * d[2] > 0.0:
        for q in range(3):
            nrm[q] = -nrm[q]
    n1 = n_wall if medium == 1 else n_poly
    n2 = n_poly if medium == 1 else n_wall
    tir = refract(d, nrm, n1, n2, newd)
    if n1 == n2:
        return 1 - medium
    if not tir and fresnel:
        cos_i = -(nrm[0] * d[0] + nrm[1] * d[1] + nrm[2] * d[2])
        if uniform(seed, FRESNEL, ray_id, event, 0) < fresnel_reflectance(cos_i, n1, n2):
            for q in range(3):
                newd[q] = d[q] + 2.0 * cos_i * nrm[q]
            tir = True
    normalise(newd)
    return medium if tir else 1 - medium


def enter_from(dirs: np.ndarray, n_in: np.ndarray, n_out: float) -> np.ndarray:
    """Refract unit directions (in place) through the T = 0 face from index ``n_out`` into ``n_in``
    (per ray); returns the statuses: REFLECTED where that is total reflection, else ACTIVE."""
    tang = dirs[:, [0, 2]] * (n_out / n_in)[:, None]
    s2 = np.sum(tang**2, axis=1)
    tir = s2 >= 1.0
    ok = ~tir
    dirs[ok, 0] = tang[ok, 0]
    dirs[ok, 2] = tang[ok, 1]
    dirs[ok, 1] = np.sqrt(1.0 - s2[ok])
    return np.where(tir, REFLECTED, ACTIVE).astype(np.int64)


def leave_into_air(dirs: np.ndarray, n_in: np.ndarray, which: np.ndarray):
    """Directions (a copy) refracted from indices ``n_in`` into air through a T face where
    ``which``; and where that is total reflection (those rows left as they were)."""
    out = dirs.copy()
    tang = dirs[:, [0, 2]] * n_in[:, None]
    s2 = np.sum(tang**2, axis=1)
    tir = s2 >= 1.0
    ok = which & ~tir
    out[ok, 0] = tang[ok, 0]
    out[ok, 2] = tang[ok, 1]
    out[ok, 1] = np.sqrt(1.0 - s2[ok])
    return out, tir
