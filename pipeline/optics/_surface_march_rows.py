"""The exact march's row tables (docs/methods.md#the-exact-method): finding, comparing and copying
the primitive rows a point evaluation lists, and which of them switched between two points."""

from numba import njit

from ..microstructure.surface import N_COLS, P_BAND, P_PLY, P_REACH, P_VESSEL_OUT


@njit(inline="always", cache=True, nogil=True)
def regime(kind):
    """Surfaces past which other primitives apply (a ray band, a vessel outline, a ply): the rows
    listed on one side say nothing of the other, so these are never stepped over blindly."""
    return kind == P_BAND or kind == P_VESSEL_OUT or kind == P_PLY


@njit(cache=True, nogil=True)
def same_key(P, i, key):
    return (P[i, 0] == key[0] and P[i, 1] == key[1] and P[i, 2] == key[2] and P[i, 3] == key[3]
            and P[i, 4] == key[4])


@njit(cache=True, nogil=True)
def find_row(P, n, key):
    for i in range(n):
        if same_key(P, i, key):
            return i
    return -1


@njit(inline="always", cache=True, nogil=True)
def copy_rows(dst, src, n):
    for i in range(n):
        for q in range(N_COLS):
            dst[i, q] = src[i, q]


@njit(cache=True, nogil=True)
def nearest(P, n, skip, key):
    """The row with the smallest clearance (not ``skip``, not a reach row), copied into ``key``;
    returns (its index or -1, the smallest clearance of the other rows, the index of that row or
    -1)."""
    a = -1
    for i in range(n):
        if P[i, 0] == P_REACH or (skip[0] > 0.0 and same_key(P, i, skip)):
            continue
        if a < 0 or P[i, 6] < P[a, 6]:
            a = i
    other = 1e300
    o = -1
    for i in range(n):
        if i == a or (skip[0] > 0.0 and same_key(P, i, skip)):
            continue
        if P[i, 6] < other:
            other = P[i, 6]
            o = i
    if a >= 0:
        for q in range(5):
            key[q] = P[a, q]
    return a, other, o


@njit(cache=True, nogil=True)
def switched(Pa, na, Pb, nb, key):
    """The primitive whose sign differs between rows Pa and Pb (the smallest |g| at b), else the
    row of smallest |g| at b, copied into ``key``; False if there is no row."""
    best = 1e300
    j = -1
    for jb in range(nb):
        if Pb[jb, 0] == P_REACH:
            continue
        for i in range(na):
            if (Pa[i, 0] == Pb[jb, 0] and Pa[i, 1] == Pb[jb, 1] and Pa[i, 2] == Pb[jb, 2]
                    and Pa[i, 3] == Pb[jb, 3] and Pa[i, 4] == Pb[jb, 4]):
                if (Pa[i, 5] < 0.0) != (Pb[jb, 5] < 0.0) and abs(Pb[jb, 5]) < best:
                    best = abs(Pb[jb, 5])
                    j = jb
                break
    if j < 0:
        # Within rounding of its root a primitive's g may keep the sign that the generator's own
        # inequality has already left: the nearest surface is the one.
        for jb in range(nb):
            if Pb[jb, 0] != P_REACH and abs(Pb[jb, 5]) < best:
                best = abs(Pb[jb, 5])
                j = jb
    if j < 0:
        return False
    for q in range(5):
        key[q] = Pb[j, q]
    return True


@njit(cache=True, nogil=True)
def far_unproven(Pb, nb, i, skip, step):
    """Whether a row at a step's end beyond a regime surface (row i), other than it and the
    primitive crossed last, may switch within the step: its clearance ball at the end does not
    reach back to the step's start (the rows of the far side say nothing of the near side)."""
    for j in range(nb):
        if j != i and not (skip[0] > 0.0 and same_key(Pb, j, skip)) and Pb[j, 6] < step:
            return True
    return False
