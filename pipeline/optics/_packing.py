"""Numba kernels that hold voxel chunks bit-packed and read voxels from them.

Coordinates are continuous voxel coordinates along [R, T, L]: voxel
(i, j, k) occupies [i, i+1) × [j, j+1) × [k, k+1).  Voxels are read through a
table of resident chunks, each held bit-packed (one bit per voxel, rows
along L: pack_chunks).
"""

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from .._intrinsics import item_pointer, splat

# Voxel lookup results besides 0 (polymer) and 1 (wall).
MISSING = 254
OUTSIDE = 253


@njit(inline="always", cache=True, nogil=True)
def voxel_at(bits, table, box, cs, shape, i, j, k):
    """Phase of voxel (i, j, k): 0/1, MISSING if its chunk is not resident, OUTSIDE."""
    ci = i // cs[0]
    cj = j // cs[1]
    ck = k // cs[2]
    a = ci - box[0]
    b = cj - box[1]
    c = ck - box[2]
    if a < 0 or b < 0 or c < 0 or a >= table.shape[0] or b >= table.shape[1] or c >= table.shape[2]:
        return MISSING
    s = table[a, b, c]
    if s == -2:
        return OUTSIDE
    if s < 0:
        return MISSING
    if (shape[0] > 0 and (i < 0 or i >= shape[0])) or (shape[2] > 0 and (k < 0 or k >= shape[2])):
        return OUTSIDE  # in the last, partly filled chunk of a finite volume
    ok = k - ck * cs[2]
    return np.uint8((bits[s, i - ci * cs[0], j - cj * cs[1], ok >> 6] >> np.uint64(ok & 63)) & np.uint64(1))


MASK_SEG = 16  # L voxels per segment of the row masks (divides 64)


def mask_segments(n_l):
    """Segments of MASK_SEG voxels in a chunk row of n_l voxels (the last one may be shorter)."""
    return -(-n_l // MASK_SEG)


def pack_chunks(voxels, bits, masks, slots, n_l):
    """Bit-pack chunks lying side by side along L into their slots, and name their uniform rows.

    ``voxels`` [R, T, L] (1 = wall) holds len(slots) chunks of ``n_l`` voxels
    along L (the last may be shorter): chunk q goes to bits[slots[q]] and
    masks[slots[q]].  Packed together, the rows of a volume in memory are
    read in one pass instead of a chunk's piece of each.

    Bit b of word w of row (i, j) is voxel (i, j, 64·w + b): rows run along
    L, the fibre axis, so a row of a normal window is one or two word reads
    and usually all wall or all polymer.  A chunk may be smaller than the
    slot (the last chunks of a finite volume): the rest reads as polymer,
    and the kernels treat it as outside.

    masks[slot, i, s, 0, w] bit b: row (i, 64·w + b) is all wall over
    segment s, the voxels [MASK_SEG·s, MASK_SEG·(s + 1)) of the slot's
    ``n_l`` along L; masks[slot, i, s, 1, w]: all polymer there.  The normal
    window skips such rows, or adds their weights without reading them, when
    every segment its L range meets says so (a row of wood varies slowly
    along the fibres: over 16 voxels it is uniform where over a whole chunk
    it often is not).  The padding of a partial chunk reads as polymer, so
    its rows are never all wall there.

    Returns False if a voxel is neither 0 nor 1 (the slots then hold garbage).
    """
    if voxels.dtype == np.bool_:
        voxels = voxels.view(np.uint8)
    elif voxels.dtype != np.uint8:
        if np.any((voxels != 0) & (voxels != 1)):
            return False
        voxels = voxels.astype(np.uint8)
    if voxels.shape[2] and voxels.strides[2] != 1:
        voxels = np.ascontiguousarray(voxels)  # rows contiguous along L
    return _pack_rows(voxels, bits, masks, np.asarray(slots, np.int64), n_l)


@intrinsic
def byte_masks64(typingctx, arr, index):
    """(nonzero, above one) of the 64 bytes arr[index], arr[index + 1], ... along arr's
    last, contiguous axis: bit b of each is set where byte b is != 0, > 1.

    One vector compare per 64 bytes, whatever the vector width of the CPU.
    """
    sig = types.UniTuple(types.uint64, 2)(arr, index)

    def codegen(context, builder, signature, args):
        ptr = item_pointer(context, builder, signature, args)
        vt = ir.VectorType(ir.IntType(8), 64)
        v = builder.load(builder.bitcast(ptr, vt.as_pointer()), align=1)
        i64 = ir.IntType(64)
        nonzero = builder.bitcast(builder.icmp_unsigned("!=", v, ir.Constant(vt, None)), i64)
        above = builder.bitcast(builder.icmp_unsigned(">", v, ir.Constant(vt, [1] * 64)), i64)
        return context.make_tuple(builder, signature.return_type, [nonzero, above])

    return sig, codegen


@intrinsic
def field_flags64(typingctx, arr, index, shift, field):
    """(all ones, all zero) of a bit field in 64 words arr[index], arr[index + 1], ...
    along arr's last, contiguous axis: bit b of each is set where
    (word b >> shift) & field equals ``field``, equals 0."""
    sig = types.UniTuple(types.uint64, 2)(arr, index, types.uint64, types.uint64)

    def codegen(context, builder, signature, args):
        ptr = item_pointer(context, builder, signature, args)
        i64 = ir.IntType(64)
        vt = ir.VectorType(i64, 64)
        v = builder.load(builder.bitcast(ptr, vt.as_pointer()), align=8)

        shift, field = splat(builder, vt, args[2]), splat(builder, vt, args[3])
        f = builder.and_(builder.lshr(v, shift), field)
        ones = builder.bitcast(builder.icmp_unsigned("==", f, field), i64)
        zero = builder.bitcast(builder.icmp_unsigned("==", f, ir.Constant(vt, None)), i64)
        return context.make_tuple(builder, signature.return_type, [ones, zero])

    return sig, codegen


@njit(cache=True, nogil=True)
def _pack_rows(voxels, bits, masks, slots, n_l):
    """pack_chunks of uint8 voxels whose rows are contiguous along L: 64 voxels per
    compare, then each R plane's row masks 64 rows per compare from a copy of
    its words laid out along T.  Returns False if a voxel is neither 0 nor 1."""
    nR, nT, n_all = voxels.shape
    cR, cT, nw = bits.shape[1:]
    ntw = masks.shape[4]
    along_t = np.zeros((slots.shape[0], nw, 64 * ntw), np.uint64)  # an R plane's words [chunk, word, T]
    for q in range(slots.shape[0]):
        if nR < cR or nT < cT or n_all - q * n_l < 64 * nw:
            bits[slots[q]] = 0
    bad = np.uint64(0)
    for i in range(cR):
        if i < nR:
            for j in range(nT):
                for q in range(slots.shape[0]):
                    sq = slots[q]
                    at = q * n_l
                    nL = min(n_l, n_all - at)
                    whole = min(nL // 64, nw)
                    for w in range(whole):
                        word, above = byte_masks64(voxels, (i, j, at + 64 * w))
                        bits[sq, i, j, w] = word
                        along_t[q, w, j] = word
                        bad |= above
                    if whole < nw:
                        word = np.uint64(0)
                        for k in range(64 * whole, min(nL, 64 * nw)):
                            x = voxels[i, j, at + k]
                            bad |= np.uint64(x > 1)
                            word |= np.uint64(x != 0) << np.uint64(k - 64 * whole)
                        bits[sq, i, j, whole] = word
                        along_t[q, whole, j] = word
        elif i == nR:
            along_t[:] = 0  # the padding planes of partial chunks
        for q in range(slots.shape[0]):
            for s in range(masks.shape[2]):
                a = MASK_SEG * s
                field = (np.uint64(1) << np.uint64(min(MASK_SEG, n_l - a))) - np.uint64(1)
                for tw in range(ntw):
                    full, empty = field_flags64(along_t, (q, a >> 6, 64 * tw), np.uint64(a & 63), field)
                    if 64 * tw + 64 > cT:  # no rows beyond the slot (their zeros are never full)
                        empty &= (np.uint64(1) << np.uint64(cT - 64 * tw)) - np.uint64(1)
                    masks[slots[q], i, s, 0, tw] = full
                    masks[slots[q], i, s, 1, tw] = empty
    return bad == 0


@njit(cache=True, nogil=True)
def mark_boxes(lo, hi, grid):
    """grid[i, j, k] = True in every box [lo[r], hi[r]] (inclusive; empty where hi < lo)."""
    for r in range(lo.shape[0]):
        for i in range(lo[r, 0], hi[r, 0] + 1):
            for j in range(lo[r, 1], hi[r, 1] + 1):
                for k in range(lo[r, 2], hi[r, 2] + 1):
                    grid[i, j, k] = True


@njit(cache=True, nogil=True)
def phases_at(bits, table, box, cs, shape, vox, out):
    """out[r] = voxel_at(vox[r]): the phase each ray starts in (or MISSING, OUTSIDE)."""
    for r in range(vox.shape[0]):
        out[r] = voxel_at(bits, table, box, cs, shape, vox[r, 0], vox[r, 1], vox[r, 2])


@njit(cache=True, nogil=True)
def read_box(bits, table, box, cs, shape, ii, jj, kk, out):
    """out[a, b, c] = voxel (ii[a], jj[b], kk[c]) of the resident chunks (MISSING where not)."""
    for a in range(ii.size):
        for b in range(jj.size):
            for c in range(kk.size):
                out[a, b, c] = voxel_at(bits, table, box, cs, shape, ii[a], jj[b], kk[c])


@njit(inline="always", cache=True, nogil=True)
def chunk_of(cs, i, j, k):
    return i // cs[0], j // cs[1], k // cs[2]


@njit(inline="always", cache=True, nogil=True)
def chunk_slot(table, box, c0, c1, c2):
    """Table entry of chunk (c0, c1, c2): a slot, -2 outside a finite volume, -1 not resident."""
    return table_entry(table, c0 - box[0], c1 - box[1], c2 - box[2])


@njit(inline="always", cache=True, nogil=True)
def table_entry(table, a, b, c):
    """table[a, b, c] (indices relative to the table's box), -1 beyond the table."""
    if a < 0 or b < 0 or c < 0 or a >= table.shape[0] or b >= table.shape[1] or c >= table.shape[2]:
        return -1
    return table[a, b, c]
