"""A grey-level scan traced on its iso-surface (method ``iso``, docs/methods.md#iso-surfaces).

A µCT or FIB-SEM volume records, in each voxel, how much wall it holds; binarising it throws away
where between two voxel centres the wall really is.  :class:`IsoVolume` keeps it: the field is the
trilinear interpolation of the grey levels between voxel centres, the wall is where it exceeds a
threshold (given, or Otsu's from the data), crossings are roots of the interpolant along each ray
(:mod:`pipeline.optics._iso_march`) and normals its gradient.  It is a surface medium: the faces
are handled by :func:`pipeline.optics.faces.through_faces` as for every medium.

The volume is read lazily, in blocks of :data:`BLOCK`³ cells, as the rays reach them, into a pool
of at most ``memory_bytes``; a NumPy array, a memory-mapped ``.npy`` or a Zarr array is read only
where rays go, in its own data type (uint8, uint16, float32 or float64; others as float64).  A Zarr
array is read chunk by chunk through :class:`ChunkReader`, so that a block and its halo, which
straddle the store's chunks, decompress each chunk once while it is kept.
"""

from __future__ import annotations

import collections
import itertools
import math
import threading

import numpy as np

from ..microstructure.grey import gaussian_part
from ..params import ParameterError
from ._iso_march import march
from .interface import NEEDS_CHUNK

OTSU_BINS = 256
BLOCK = 32  # cells a side of a block of the volume read at a time
MEMORY_BYTES = 512 * 2 ** 20  # the pool of blocks one trace holds at most
SAMPLE_VOXELS = 2 ** 24  # Otsu's threshold and the data's range from at most this many voxels
CHUNK_BYTES = 64 * 2 ** 20  # decompressed chunks of a Zarr volume kept at most
# The pre-filter `twray trace --method iso` applies unless told (σ [µm]): every smoothed row of
# results/accuracy.md used it, each closer to `exact` in FWHM_L than unsmoothed (25 woods at 0.5 µm:
# within 5 % and 1 haze point only smoothed); small enough that balsa's 1.4 µm walls stay above ½.
SMOOTH_UM = 0.5
_NATIVE = (np.uint8, np.uint16, np.float32, np.float64)


class ChunkReader:
    """Regions of a chunked array (a Zarr array) read chunk by chunk, the decompressed chunks kept
    (at most ``memory_bytes``, the least recently read going): a region that straddles chunks
    decompresses each once while it is kept.  ``decompressed`` counts the chunks read from the
    store; ``whole_reads`` what reading each region at once would have decompressed."""

    def __init__(self, array, memory_bytes: int = CHUNK_BYTES):
        self.array, self.shape = array, tuple(int(n) for n in array.shape)
        self.chunks = tuple(int(c) for c in array.chunks)
        self.memory_bytes = int(memory_bytes)
        self.held: collections.OrderedDict = collections.OrderedDict()
        self.bytes = self.decompressed = self.whole_reads = 0
        self._lock = threading.Lock()

    @staticmethod
    def applies(array) -> bool:
        """Whether ``array`` is a Zarr array (read chunk by chunk)."""
        return type(array).__module__.split(".")[0] == "zarr" and hasattr(array, "chunks")

    def __getitem__(self, region: tuple) -> np.ndarray:
        spans = [r.indices(n)[:2] for r, n in zip(region, self.shape)]
        out = np.empty([max(b - a, 0) for a, b in spans], self.array.dtype)
        if out.size == 0:
            return out
        ranges = [range(a // c, (b - 1) // c + 1) for (a, b), c in zip(spans, self.chunks)]
        with self._lock:
            self.whole_reads += math.prod(len(r) for r in ranges)
            for idx in itertools.product(*ranges):
                data = self._chunk(idx)
                src, dst = [], []
                for (a, b), i, c in zip(spans, idx, self.chunks):
                    lo, hi = max(a, i * c), min(b, (i + 1) * c)
                    src.append(slice(lo - i * c, hi - i * c))
                    dst.append(slice(lo - a, hi - a))
                out[tuple(dst)] = data[tuple(src)]
        return out

    def _chunk(self, idx: tuple) -> np.ndarray:
        data = self.held.get(idx)
        if data is not None:
            self.held.move_to_end(idx)
            return data
        data = np.asarray(self.array[tuple(slice(i * c, min((i + 1) * c, n))
                                           for i, c, n in zip(idx, self.chunks, self.shape))])
        self.decompressed += 1
        self.held[idx] = data
        self.bytes += data.nbytes
        while self.bytes > self.memory_bytes and len(self.held) > 1:
            _, gone = self.held.popitem(last=False)
            self.bytes -= gone.nbytes
        return data


def otsu_threshold(values: np.ndarray, bins: int = OTSU_BINS) -> float:
    """Otsu's threshold of ``values``: the grey level between the two classes of largest
    between-class variance, at the edge of the bin it ends (one of ``bins`` over the data's range)."""
    v = np.asarray(values, np.float64).ravel()
    lo, hi = float(v.min()), float(v.max())
    if not lo < hi:
        raise ParameterError(f"`volume` holds one grey level ({lo:g}): no threshold separates wall from polymer")
    counts, edges = np.histogram(v, bins=bins, range=(lo, hi))
    p = counts / counts.sum()
    centres = 0.5 * (edges[:-1] + edges[1:])
    w0 = np.cumsum(p)
    m = np.cumsum(p * centres)
    with np.errstate(divide="ignore", invalid="ignore"):
        between = (m[-1] * w0 - m) ** 2 / (w0 * (1.0 - w0))
    between[~np.isfinite(between)] = -1.0
    return float(edges[int(np.argmax(between)) + 1])


class IsoVolume:
    """A grey-level volume (R, T, L) of ``voxel_um`` voxels, its corner at the origin, as the
    surface of level ``iso`` (None: Otsu's threshold of the data); wall above it.

    ``array``: anything sliced like a NumPy array (a memory-mapped ``.npy``, a Zarr array), read in
    blocks of ``block``³ cells only where rays go, at most ``memory_bytes`` of them at a time.  The
    ``smooth_um`` > 0: the field is the volume smoothed by a Gaussian of that σ [µm] (a pre-filter
    against noise, applied block by block with the kernel's halo: the same values as the whole
    volume smoothed at once).  The
    threshold and the check that it lies within the data use every voxel of a volume of up to
    :data:`SAMPLE_VOXELS`, else every k-th L slice, or what the array's own ``sample()`` returns
    (``iso_sample`` says which); every block read is checked for non-finite values."""

    medium_kind = "fields"

    def __init__(self, array, *, voxel_um: float, iso: float | None = None, block: int = BLOCK,
                 memory_bytes: int = MEMORY_BYTES, smooth_um: float = 0.0):
        if not (isinstance(voxel_um, (int, float)) and math.isfinite(voxel_um) and voxel_um > 0):
            raise ParameterError(f"`voxel_um` must be > 0 µm, got voxel_um={voxel_um!r}")
        shape = tuple(int(n) for n in np.shape(array))
        if len(shape) != 3 or min(shape) < 1:
            raise ParameterError(f"`volume` must be a 3-D array (R, T, L) of grey levels, got shape {shape}")
        if isinstance(block, bool) or not isinstance(block, int) or block < 1:
            raise ParameterError(f"`block` must be an integer >= 1, got block={block!r}")
        self.array = array if hasattr(array, "dtype") else np.asarray(array)
        self.chunk_reader = ChunkReader(array) if ChunkReader.applies(array) else None
        dtype = np.dtype(self.array.dtype)
        if dtype.kind not in "biuf":
            raise ParameterError(f"`volume` must hold numbers (grey levels), got dtype {dtype}")
        self.dtype = np.dtype(np.uint8) if dtype.kind == "b" else next(
            (np.dtype(t) for t in _NATIVE if np.dtype(t) == dtype), np.dtype(np.float64))
        if isinstance(smooth_um, bool) or not (isinstance(smooth_um, (int, float)) and math.isfinite(smooth_um)
                                               and smooth_um >= 0):
            raise ParameterError(f"`smooth_um` must be a number >= 0 µm, got smooth_um={smooth_um!r}")
        self.smooth_um = float(smooth_um)
        if self.smooth_um > 0 and self.dtype != np.float64:
            self.dtype = np.dtype(np.float32)  # a smoothed field is not integers
        self.shape = shape
        self.block = int(block)
        self.memory_bytes = int(memory_bytes)
        self.voxel_um = float(voxel_um)
        self.thickness_um = shape[1] * self.voxel_um
        step = max(1, math.ceil(math.prod(shape) / SAMPLE_VOXELS))
        if hasattr(self.array, "sample"):  # a volume that says which of its grey levels to sample
            self.iso_sample = "the volume's own sample"
            sample = np.asarray(self.array.sample(), self.dtype)
        else:
            self.iso_sample = "every voxel" if step == 1 else f"every {step}th L slice"
            sample = self._raw((slice(None), slice(None), slice(None, None, step)), (0, 0, 0))
        lo, hi = float(sample.min()), float(sample.max())
        self.iso_from = "given"
        if iso is None:
            iso, self.iso_from = otsu_threshold(sample), "otsu"
        if not (isinstance(iso, (int, float)) and math.isfinite(iso) and lo <= iso < hi):
            raise ParameterError(f"`iso` must lie in the volume's grey levels [{lo:g}, {hi:g}), got iso={iso!r}")
        self.iso = float(iso)
        self.blocks_read = 0  # blocks read by the traces so far (a block read again counts again)
        self._blocks = None  # the pool of blocks read, kept between traces
        self._lock = threading.Lock()

    def _read(self, region, first) -> np.ndarray:
        """The voxels of ``region`` (a tuple of slices) in the pool's data type, checked finite
        (``first``: the region's first voxel, to name a bad one), smoothed when ``smooth_um``
        (read with the halo the kernel reaches, so a block is that part of the whole volume smoothed)."""
        if self.smooth_um > 0 and all(r.step in (None, 1) for r in region):
            spans = [r.indices(n)[:2] for r, n in zip(region, self.shape)]
            return gaussian_part(lambda a, b: self._raw(tuple(slice(x, y) for x, y in zip(a, b)), a),
                                 [a for a, _ in spans], [b for _, b in spans], self.shape,
                                 self.smooth_um / self.voxel_um, self.dtype)
        return self._raw(region, first)

    def _raw(self, region, first) -> np.ndarray:
        chunked = self.chunk_reader is not None and all(r.step in (None, 1) for r in region)
        data = self.chunk_reader[region] if chunked else np.asarray(self.array[region])
        if data.dtype != self.dtype:
            data = data.astype(self.dtype)
        if self.dtype.kind == "f":
            bad = ~np.isfinite(data)
            if bad.any():
                at = tuple(int(i) + o for i, o in zip(np.argwhere(bad)[0], first))
                raise ParameterError(f"`volume` must hold finite grey levels, got {int(bad.sum())} that are not "
                                     f"(the first at voxel {at})")
        return data

    def field(self, points_um) -> np.ndarray:
        """The interpolated grey level at ``points_um`` (N, 3) [µm] (constant beyond the outermost
        voxel centres)."""
        p = np.asarray(points_um, np.float64).reshape(-1, 3) / self.voxel_um - 0.5
        i0 = np.floor(p).astype(np.int64)
        f = p - i0
        out = np.zeros(len(p))
        if len(p) == 0:
            return out
        dims = np.array(self.shape)
        lo = np.clip(i0.min(axis=0), 0, dims - 1)
        hi = np.clip(i0.max(axis=0) + 1, 0, dims - 1)
        box = self._read(tuple(slice(a, b + 1) for a, b in zip(lo, hi)), lo)
        for a in (0, 1):
            for b in (0, 1):
                for e in (0, 1):
                    idx = [np.clip(i0[:, q] + o, 0, self.shape[q] - 1) - lo[q] for q, o in enumerate((a, b, e))]
                    w = ((f[:, 0] if a else 1 - f[:, 0]) * (f[:, 1] if b else 1 - f[:, 1])
                         * (f[:, 2] if e else 1 - f[:, 2]))
                    out += w * box[idx[0], idx[1], idx[2]].astype(np.float64)
        return out

    def entry_phase(self, origins_um) -> np.ndarray:
        """1 (wall) where the field at the entry point exceeds ``iso``, 0 elsewhere; 255 outside
        the volume's R-L face."""
        pos = np.array(origins_um, np.float64, copy=True).reshape(-1, 3)
        pos[:, 1] = 0.0
        inside = ((pos[:, 0] >= 0) & (pos[:, 0] <= self.shape[0] * self.voxel_um)
                  & (pos[:, 2] >= 0) & (pos[:, 2] <= self.shape[2] * self.voxel_um))
        phase = np.full(len(pos), 255, np.uint8)
        phase[inside] = (self.field(pos[inside]) > self.iso).astype(np.uint8)
        return phase

    def march_walls(self, origins_um, directions, *, n_wall: float, n_poly: float, max_events: int,
                    fresnel: bool = False, seed: int = 0, ray_ids=None) -> dict:
        """March the rays, reading each block of the volume when the first of them reaches it: round
        after round, the rays stopped for blocks go on once the blocks most of them wait for are in
        the pool (kept between traces; the least recently wanted make room), bit for bit as if the
        whole volume were.  One trace at a time marches a volume (a lock)."""
        pos = np.array(origins_um, np.float64, copy=True).reshape(-1, 3)
        pos[:, 1] = 0.0
        n = len(pos)
        ids = np.arange(n, dtype=np.int64) if ray_ids is None else np.asarray(ray_ids, np.int64)
        state = {"position": pos, "direction": np.array(directions, np.float64, copy=True).reshape(-1, 3),
                 "medium": self.entry_phase(pos), "events": np.zeros(n, np.int64), "path": np.zeros(n),
                 "cells": np.zeros(n, np.int64), "flat_normals": np.zeros(n, np.int64)}
        s0, idx, resume = np.zeros(n), np.zeros((n, 3), np.int64), np.zeros(n, bool)
        status, want = np.full(n, NEEDS_CHUNK, np.int64), np.zeros((n, 3), np.int64)
        dims = np.array(self.shape, np.int64)
        with self._lock:
            if self._blocks is None:
                self._blocks = _BlockPool(self.shape, self.block, self.dtype, self.memory_bytes)
            blocks = self._blocks
            first = True
            while (todo := np.flatnonzero(status == NEEDS_CHUNK)).size:
                if not first:  # read the blocks the stopped rays wait for
                    self.blocks_read += blocks.fetch(want[todo], self._read)
                first = False
                part = {k: np.ascontiguousarray(v[todo]) for k, v in state.items()}
                p_s0, p_idx, p_res = s0[todo], idx[todo], resume[todo]
                p_status, p_want = np.empty(len(todo), np.int64), np.zeros((len(todo), 3), np.int64)
                march(blocks.pool, blocks.slots, self.block, dims, self.voxel_um, self.iso, ids[todo], float(n_wall),
                      float(n_poly), int(max_events), bool(fresnel), np.uint64(seed), part["position"],
                      part["direction"], part["medium"], part["events"], part["path"], part["cells"],
                      part["flat_normals"], p_s0, p_idx, p_res, p_status, p_want)
                for k, v in part.items():
                    state[k][todo] = v
                s0[todo], idx[todo], resume[todo], status[todo], want[todo] = p_s0, p_idx, p_res, p_status, p_want
        return {"position": state["position"], "direction": state["direction"], "status": status,
                "events": state["events"], "path": state["path"], "medium": state["medium"],
                "cells": state["cells"], "flat_normals": state["flat_normals"]}


class _BlockPool:
    """The blocks of a volume in memory: ``pool[slot]`` holds the block ``held[slot]`` (its voxels from
    block·b, B + 1 a side, clamped to the volume) and ``slots[b]`` its slot or -1; at most
    ``memory_bytes`` of them, the least recently wanted giving way."""

    def __init__(self, shape, block: int, dtype, memory_bytes: int):
        self.shape, self.block = shape, block
        grid = tuple(-(-s // block) for s in shape)
        self.slots = np.full(grid, -1, np.int64)
        side = block + 1
        capacity = max(1, min(math.prod(grid), memory_bytes // (side ** 3 * dtype.itemsize)))
        self.pool = np.zeros((capacity, side, side, side), dtype)
        self.held = [None] * capacity
        self.last = np.full(capacity, -1, np.int64)  # when each slot was last wanted
        self.clock = 0

    def fetch(self, wanted: np.ndarray, read) -> int:
        """Read the blocks ``wanted`` (rows of block indices, one per waiting ray) not in the pool, the
        most wanted first, as far as the slots not wanted now allow, with ``read(region, first)``;
        returns how many were read."""
        self.clock += 1
        keys, counts = np.unique(wanted, axis=0, return_counts=True)
        have = self.slots[tuple(keys.T)]
        self.last[have[have >= 0]] = self.clock
        missing = [tuple(int(v) for v in keys[q]) for q in np.argsort(-counts, kind="stable") if have[q] < 0]
        free = [int(q) for q in np.argsort(self.last, kind="stable") if self.last[q] < self.clock]
        side = self.block + 1
        for key, slot in zip(missing, free):
            if self.held[slot] is not None:
                self.slots[self.held[slot]] = -1
            first = tuple(b * self.block for b in key)
            data = read(tuple(slice(f, min(f + side, s)) for f, s in zip(first, self.shape)), first)
            self.pool[(slot,) + tuple(slice(0, m) for m in data.shape)] = data
            self.slots[key], self.held[slot], self.last[slot] = slot, key, self.clock
        return min(len(missing), len(free))
