"""Voxel media: where the voxel tracer's voxels come from, user volumes and lazily generated wood.

A source hands out the voxels of a chunk on request (the last chunks of a
finite volume are smaller; the tracer reads voxels beyond it as OUTSIDE);
generated wood is unbounded along R and L, so rays that spread sideways
simply visit more chunks.
"""

from __future__ import annotations

import json
import math
import os
import threading
from pathlib import Path

import numpy as np

from ..microstructure.model import generate_block
from ..microstructure.grey import full_region
from ..lru import ByteLRU
from ..params import Grid, ParameterError, WoodParams
from ._packing import mask_segments, pack_chunks, read_box


class ArraySource:
    """A user volume (axes [R, T, L], 1 = wall, 0 = polymer) held as an array or Zarr array.

    Parameters
    ----------
    array : array-like of shape (R, T, L)
        Anything sliceable to numpy (``numpy.ndarray``, ``zarr.Array``).
    chunks : tuple of 3 int
        Chunk shape the tracer pages in.
    voxel_um : float
        Side of a voxel [µm] (what the tracer interface converts µm by).
    """

    unbounded = (False, False)
    token = None  # its voxels may change under it: never in the packed-chunk memo

    def __init__(self, array, *, chunks=(64, 64, 64), voxel_um: float = 1.0):
        if not (math.isfinite(voxel_um) and voxel_um > 0):
            raise ParameterError(f"`voxel_um` must be > 0 µm, got voxel_um={voxel_um!r}")
        if getattr(array, "ndim", None) != 3:
            raise ParameterError(f"`volume` must be a 3-D array (R, T, L), got shape {np.shape(array)}")
        if min(array.shape) < 1:
            raise ParameterError(f"`volume` must hold at least one voxel along R, T and L, got shape "
                                 f"{tuple(array.shape)}")
        self.array = array
        self.voxel_um = float(voxel_um)
        self.shape = tuple(int(s) for s in array.shape)
        self.chunks = tuple(int(min(c, s)) for c, s in zip(chunks, self.shape))

    def inside(self, idx) -> bool:
        return all(0 <= i < math.ceil(s / c) for i, s, c in zip(idx, self.shape, self.chunks))

    def get(self, idx) -> np.ndarray:
        """The voxels of chunk ``idx``; the last chunks along an axis are smaller."""
        sl = tuple(slice(i * c, min((i + 1) * c, s)) for i, c, s in zip(idx, self.chunks, self.shape))
        return np.asarray(self.array[sl])

    def get_many(self, indices) -> dict:
        return {tuple(int(i) for i in idx): self.get(idx) for idx in indices}

    def get_run(self, idx, count: int) -> np.ndarray:
        """The voxels of chunks ``idx`` and the ``count - 1`` next along L, side by side."""
        i, j, k = idx
        cR, cT, cL = self.chunks
        sl = (slice(i * cR, min((i + 1) * cR, self.shape[0])), slice(j * cT, min((j + 1) * cT, self.shape[1])),
              slice(k * cL, min((k + count) * cL, self.shape[2])))
        return np.asarray(self.array[sl])


class WoodSource:
    """Generated wood of a given thickness along T, unbounded along R and L.

    Chunks are generated on request by the model, or taken from ``store`` (a
    :class:`~pipeline.microstructure.store.WoodChunkStore` of the same wood),
    which generates and keeps the ones it does not have yet.
    """

    unbounded = (True, True)

    def __init__(self, params: WoodParams, *, thickness_um: float, voxel_um: float = 0.5,
                 seed: int = 1, chunks=(64, 64, 64), store=None, threads: int = 1):
        nT = int(round(thickness_um / voxel_um))
        if nT < 1:
            raise ParameterError(f"`thickness` must be at least one voxel, got {thickness_um:g} µm")
        self.params = params
        self.seed = int(seed)
        self.grid = Grid((0, nT, 0), float(voxel_um), (0.0, 0.0, 0.0))
        self.voxel_um = float(voxel_um)
        self.shape = (0, nT, 0)  # 0: unbounded
        self.store = store
        self.chunks = tuple(int(c) for c in (store.chunks if store is not None else chunks))
        self.threads = max(1, int(threads))  # generating chunks (not from a store) side by side
        self.generated = 0  # chunks asked of the store or generator (not those in PackedMemo)
        self.distinct: set[tuple] = set()
        # What its voxels depend on: the chunks of equal tokens are equal (PackedMemo).
        self.token = ("wood", json.dumps(params.to_dict(), sort_keys=True), self.seed, float(voxel_um),
                      nT, self.chunks)

    def inside(self, idx) -> bool:
        return 0 <= idx[1] < math.ceil(self.shape[1] / self.chunks[1])

    def get(self, idx) -> np.ndarray:
        """The voxels of chunk ``idx``; the last chunk along T is thinner."""
        return self.get_many([idx])[tuple(int(i) for i in idx)]

    def get_many(self, indices) -> dict:
        """{idx: voxels} of several chunks (through the store's :meth:`get_many`)."""
        indices = [tuple(int(i) for i in idx) for idx in indices]
        cR, cT, cL = self.chunks
        thick = {idx: min(cT, self.shape[1] - idx[1] * cT) for idx in indices}
        if self.store is not None:
            out = {idx: data[:, :thick[idx], :] for idx, data in self.store.get_many(indices).items()}
        else:
            def make(idx):
                return generate_block(self.params, self.grid, (idx[0] * cR, idx[1] * cT, idx[2] * cL),
                                      (cR, thick[idx], cL), seed=self.seed)

            if self.threads > 1 and len(indices) > 1:
                # The generator's kernels release the GIL: chunks are made side by side.
                out = dict(zip(indices, _generator_pool(self.threads).map(make, indices)))
            else:
                out = {idx: make(idx) for idx in indices}
        self.generated += len(indices)
        self.distinct.update(indices)
        return out


_POOLS: dict = {}
_POOLS_LOCK = threading.Lock()


def _generator_pool(threads: int):
    """This process's thread pool of ``threads`` for generating chunks (made once, kept)."""
    from concurrent.futures import ThreadPoolExecutor

    with _POOLS_LOCK:
        if threads not in _POOLS:
            _POOLS[threads] = ThreadPoolExecutor(threads, thread_name_prefix="twray-generate")
        return _POOLS[threads]


def load_volume(path: str | Path):
    """Open a user volume: ``.npy`` (memory-mapped), Zarr (a twray store or a bare array), or a folder of
    TIFF slices (:class:`TiffStack`); each is read where a trace needs it."""
    path = Path(path)
    if not path.exists():
        raise ParameterError(f"`volume` must be an existing .npy, .zarr or TIFF folder, got {str(path)!r}")
    if path.suffix == ".npy":
        return np.load(path, mmap_mode="r")
    if path.is_dir() and (path / "zarr.json").exists():
        import zarr

        from ..microstructure.volume import WoodVolume
        from ..publish import written_by_twray

        if written_by_twray(path) and "twray" in zarr.open_group(path, mode="r").attrs:
            return WoodVolume.open(path)  # a lazy volume's chunks are generated as they are read
        node = zarr.open(path, mode="r")
        if hasattr(node, "shape"):
            return node
        return node["0"]
    if path.is_dir():
        import tifffile

        files = sorted(p for p in path.iterdir() if p.suffix.lower() in (".tif", ".tiff"))
        if not files:
            raise ParameterError(f"`volume` folder holds no .tif slices: {str(path)!r}")
        return TiffStack(files)
    raise ParameterError(f"`volume` must be .npy, .zarr or a folder of TIFF slices, got {str(path)!r}")


TIFF_CACHE_BYTES = 256 * 2 ** 20  # the slices a TiffStack keeps


class TiffStack:
    """A folder of TIFF slices (one per L, in name order; each R × T) as a 3-D array (R, T, L) whose
    slices are read when a part of the volume needs them (``stack[i0:i1, j0:j1, k0:k1]``), the
    most recently read kept up to :data:`TIFF_CACHE_BYTES`."""

    ndim = 3

    def __init__(self, files):
        import tifffile

        self.files = list(files)
        with tifffile.TiffFile(self.files[0]) as first:
            page = first.pages[0]
            shape, self.dtype = tuple(int(n) for n in page.shape), np.dtype(page.dtype)
        if len(shape) != 2:
            raise ParameterError(f"`volume` TIFF slices must each be 2-D (R × T), got shape {shape} in "
                                 f"{str(self.files[0])!r}")
        self.shape = (*shape, len(self.files))
        self._slices = ByteLRU(TIFF_CACHE_BYTES)

    def _slice(self, k: int) -> np.ndarray:
        import tifffile

        data = self._slices.get(k)
        if data is None:
            data = tifffile.imread(self.files[k])
            if data.shape != self.shape[:2]:
                raise ParameterError(f"`volume` TIFF slices must all have one shape {self.shape[:2]}, got "
                                     f"{data.shape} in {str(self.files[k])!r}")
            self._slices.put(k, data, data.nbytes)
        return data

    def __getitem__(self, region) -> np.ndarray:
        region = full_region(region)
        if not all(isinstance(r, slice) for r in region):
            return np.asarray(self[:, :, :])[region]
        ks = range(*region[2].indices(self.shape[2]))
        out = np.empty((*np.empty(self.shape[:2], bool)[region[:2]].shape, len(ks)), self.dtype)
        for q, k in enumerate(ks):
            out[:, :, q] = self._slice(k)[region[:2]]
        return out

    def __array__(self, dtype=None, copy=None):
        return np.asarray(self[:, :, :], dtype)


def _runs_along_l(keys) -> list[list[tuple]]:
    """Chunk keys (i, j, k) grouped into runs of consecutive k at the same (i, j)."""
    runs: list[list[tuple]] = []
    for key in sorted(keys):
        last = runs[-1][-1] if runs else None
        if last is not None and last[:2] == key[:2] and last[2] + 1 == key[2]:
            runs[-1].append(key)
        else:
            runs.append([key])
    return runs


class PackedMemo(ByteLRU):
    """The bit-packed chunks (bits and row masks) this process made, least recently used
    dropped beyond ``limit`` bytes; keyed by (source token, chunk index).

    The tasks of a worker trace over the same wood again and again: the shards
    of a beam, the scenes of a study that share a microstructure, the row
    blocks of a camera image and its neighbours (Figure 5: 66 548 chunk loads
    of 10 899 distinct chunks).  A chunk found here costs a 36 KB copy instead
    of a file read, a Zstandard decode and a packing pass (about 0.4 ms for
    64³).  Thread-safe; the entries are copies, so callers may overwrite
    their slots.
    """

    @property
    def limit(self) -> int:
        """Bytes kept at most: ``limit`` if given, else the environment's
        ``TWRAY_PACKED_MEMO_MB`` (MiB, default 1024, 29 000 chunks of 64³; 0 turns the memo off)."""
        if self._limit is None:
            raw = os.environ.get("TWRAY_PACKED_MEMO_MB", "1024")
            try:
                mb = int(raw)
            except ValueError:
                mb = -1
            if mb < 0:
                raise ParameterError(f"`TWRAY_PACKED_MEMO_MB` must be an integer >= 0 (MiB), got {raw!r}")
            self._limit = mb << 20
        return self._limit

    def fetch(self, key, bits, masks, slot) -> bool:
        """Copy entry ``key`` into ``bits[slot]`` and ``masks[slot]``; False if absent."""
        entry = self.get(key)
        if entry is None:
            return False
        bits[slot] = entry[0]
        masks[slot] = entry[1]
        return True

    def keep(self, key, bits, masks, slot) -> None:
        """Remember ``bits[slot]`` and ``masks[slot]`` as entry ``key``."""
        size = bits[slot].nbytes + masks[slot].nbytes
        if size <= self.limit:
            self.put(key, (bits[slot].copy(), masks[slot].copy()), size)


_PACKED = PackedMemo()  # this process's; its limit from TWRAY_PACKED_MEMO_MB

# Buffers of finished caches, reused by the next ChunkCache of this process
# (a worker traces shard after shard): pages it has written need not be
# faulted in again.  At most _SPARE_KEPT are kept, the most recent ones.
_SPARE: list[tuple[np.ndarray, np.ndarray]] = []
_SPARE_KEPT = 2
_SPARE_LOCK = threading.Lock()


class ChunkCache:
    """The resident chunks, bit-packed (``bits``), and the lookup table the kernels read.

    Keeps at most ``capacity`` chunks (or the slots of the reused buffers,
    if more), evicting the least recently requested.  :meth:`release` hands
    the buffers on to the next cache.
    """

    def __init__(self, source, capacity: int = 256):
        self.source = source
        self.slots: dict[tuple, int] = {}
        self.outside: set[tuple] = set()
        self.last_use: dict[tuple, int] = {}
        self.tick = 0
        # One bit per voxel (pack_chunks): 1/8 of the chunks' bytes; pages on use.
        # Per slot, R index and L segment, the all-wall and all-polymer rows as
        # bits along T (pack_chunks).
        self.bits, self.masks = self._buffers(max(1, int(capacity)))
        self.capacity = self.bits.shape[0]
        self.free = list(range(self.capacity))[::-1]
        self.loads = 0  # chunks made resident
        self.reused = 0  # of which copied from the process's PackedMemo
        self._rebuild()

    def _buffers(self, capacity):
        """A finished cache's buffers of this chunk shape with enough slots, or new ones."""
        with _SPARE_LOCK:
            for q, (bits, masks) in enumerate(_SPARE):
                # Both shapes: chunks 40 and 64 voxels long along L pack into one word a row,
                # but their row masks have 3 and 4 segments.
                if (bits.shape[1:] == self._bits_shape and masks.shape[1:] == self._masks_shape
                        and bits.shape[0] >= capacity):
                    return _SPARE.pop(q)
        return (np.empty((capacity,) + self._bits_shape, np.uint64),
                np.empty((capacity,) + self._masks_shape, np.uint64))

    def release(self) -> None:
        """Give the buffers to the next cache of this process; this one holds nothing after."""
        bits, masks = self.bits, self.masks
        self.bits = self.masks = None
        self.slots.clear()
        with _SPARE_LOCK:
            _SPARE.append((bits, masks))
            del _SPARE[:-_SPARE_KEPT]

    @property
    def _bits_shape(self) -> tuple:
        cR, cT, cL = self.source.chunks
        return (cR, cT, -(-cL // 64))

    @property
    def _masks_shape(self) -> tuple:
        cR, cT, cL = self.source.chunks
        return (cR, mask_segments(cL), 2, -(-cT // 64))

    @property
    def chunk_shape(self) -> np.ndarray:
        return np.asarray(self.source.chunks, np.int64)

    def _rebuild(self):
        keys = list(self.slots) + list(self.outside)
        if not keys:
            self.box = np.zeros(3, np.int64)
            self.table = np.full((1, 1, 1), -1, np.int32)
            return
        keys = np.array(keys, np.int64)
        lo = keys.min(axis=0)
        self.box = lo
        self.table = np.full(tuple(keys.max(axis=0) - lo + 1), -1, np.int32)
        rel = keys - lo
        self.table[rel[:, 0], rel[:, 1], rel[:, 2]] = np.concatenate(
            [np.fromiter(self.slots.values(), np.int32, len(self.slots)), np.full(len(self.outside), -2, np.int32)])

    def require(self, keys, keep=()) -> None:
        """Make the chunks ``keys`` resident (or known to be outside).

        Chunks in ``keys`` and ``keep`` (those live rays stand in) are never
        evicted; when they alone exceed the capacity the pool grows rather
        than thrash.
        """
        self.tick += 1
        keys = list(dict.fromkeys(tuple(map(int, k)) for k in keys))
        protected = set(keys)
        protected.update(keep)  # (i, j, k) tuples of ints
        for k in protected:
            self.last_use[k] = self.tick
        new = [k for k in dict.fromkeys(keys) if k not in self.slots and k not in self.outside]
        if not new:
            return
        inside = [k for k in new if self.source.inside(k)]
        self.outside.update(k for k in new if not self.source.inside(k))
        evictable = sorted((k for k in self.slots if k not in protected),
                           key=lambda k: self.last_use.get(k, 0))
        while len(self.free) < len(inside) and evictable:
            self.free.append(self.slots.pop(evictable.pop(0)))
        if len(self.free) < len(inside):
            grow = len(inside) - len(self.free)
            self.free.extend(range(self.bits.shape[0], self.bits.shape[0] + grow))
            self.bits = np.concatenate([self.bits, np.empty((grow,) + self._bits_shape, np.uint64)])
            self.masks = np.concatenate([self.masks, np.empty((grow,) + self._masks_shape, np.uint64)])
            self.capacity = self.bits.shape[0]
        token = getattr(self.source, "token", None)
        if token is not None and _PACKED.limit > 0:
            # Chunks this process packed before (an earlier shard or camera task)
            # are copied from the memo instead of read, decoded and packed again.
            missed = []
            for k in inside:
                slot = self.free[-1]
                if _PACKED.fetch((token, k), self.bits, self.masks, slot):
                    self.slots[k] = self.free.pop()
                    self.loads += 1
                    self.reused += 1
                else:
                    missed.append(k)
            inside = missed
        if hasattr(self.source, "get_run"):
            # Runs of chunks along L are read and packed together (whole rows of a volume).
            runs = _runs_along_l(inside)
            chunks = None
        else:
            runs = [[k] for k in inside]
            chunks = self.source.get_many(inside)
        for run in runs:
            slots = [self.free.pop() for _ in run]
            voxels = np.asarray(chunks.pop(run[0]) if chunks is not None else self.source.get_run(run[0], len(run)))
            if not pack_chunks(voxels, self.bits, self.masks, slots, self.source.chunks[2]):
                bad = voxels[(voxels != 0) & (voxels != 1)]
                got = f"values up to {bad.max()}" if bad.max() > 1 else f"the value {bad.min()}"
                raise ParameterError(f"`volume` must hold 0 (polymer) and 1 (wall) only, got {got}")
            self.slots.update(zip(run, slots))
            self.loads += len(run)
            if token is not None:
                for k, slot in zip(run, slots):
                    _PACKED.keep((token, k), self.bits, self.masks, slot)
        self._rebuild()

    def voxels(self, lo, shape) -> np.ndarray:
        """A small box of voxels (clamped at the T faces) through the resident chunks."""
        cs = self.source.chunks
        idx = [np.arange(l, l + n, dtype=np.int64) for l, n in zip(lo, shape)]
        idx[1] = np.clip(idx[1], 0, self.source.shape[1] - 1)
        for a in (0, 2):
            if self.source.shape[a] > 0:
                idx[a] = np.clip(idx[a], 0, self.source.shape[a] - 1)
        need = {(i // cs[0], j // cs[1], k // cs[2]) for i in idx[0][[0, -1]]
                for j in idx[1][[0, -1]] for k in idx[2][[0, -1]]}
        self.require(need)
        out = np.empty(shape, np.uint8)
        read_box(self.bits, self.table, self.box, self.chunk_shape, np.asarray(self.source.shape, np.int64),
                   *idx, out)
        return out
