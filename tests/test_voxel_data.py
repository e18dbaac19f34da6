"""The voxel backend's data: chunks held and packed, row masks, the memo of packed chunks, chunk
sets of live rays, its settings' bounds, and the smoothed wall its normals step on."""

import numpy as np
import pytest
from scipy import ndimage

from pipeline.optics import _normals, _packing
from pipeline.optics.sources import ArraySource, ChunkCache, WoodSource
from pipeline.optics.rays import square_beam
from pipeline.optics.settings import settings_for
from pipeline.optics.voxels import trace_in_voxels
from pipeline.params import ParameterError, build_params

N_WALL, N_POLY = 1.50, 1.49


def resident(vol, chunks):
    """A ChunkCache holding every chunk of ``vol`` and the kernels' view of it."""
    src = ArraySource(vol, chunks=chunks)
    cache = ChunkCache(src, capacity=1000)
    cache.require(np.ndindex(*(-(-s // c) for s, c in zip(vol.shape, src.chunks))))
    return cache, (cache.bits, cache.table, cache.box, cache.chunk_shape, np.asarray(vol.shape, np.int64))


def window_view(cache, view, masks=None):
    """The arguments of smoothed_wall before the point: the view with the chunks' row masks."""
    return (view[0], cache.masks if masks is None else masks) + view[1:]


def test_row_masks_name_exactly_the_all_wall_and_all_polymer_rows_of_each_segment():
    rng = np.random.default_rng(5)
    vol = (rng.random((40, 70, 150)) < 0.5).astype(np.uint8)
    vol[:, ::3, :] = 1  # whole rows of wall and of polymer, and some with one voxel changed
    vol[:, 1::3, :] = 0
    vol[:, 2::6, 20:40] = 1  # rows uniform over some L segments only
    vol[rng.integers(0, 40, 200), rng.integers(0, 70, 200), rng.integers(0, 150, 200)] ^= 1
    cache, _ = resident(vol, (16, 70, 72))  # rows of 72 voxels: two words, the second partly used
    seg = _packing.MASK_SEG
    assert cache.masks.shape[2] == -(-72 // seg) == 5  # the last segment holds 8 voxels
    for key, s in cache.slots.items():
        sl = tuple(slice(k * c, (k + 1) * c) for k, c in zip(key, cache.source.chunks))
        chunk = vol[sl]
        bits = np.unpackbits(cache.masks[s].view(np.uint8), axis=-1, bitorder="little")[..., :70]
        for g in range(5):
            part = chunk[:, :, g * seg:(g + 1) * seg]
            # The padding of a partial chunk reads as polymer: its rows are never all wall there.
            full = part.all(axis=2) if chunk.shape[2] >= min((g + 1) * seg, 72) else np.zeros(part.shape[:2], bool)
            assert np.array_equal(bits[: chunk.shape[0], g, 0, : chunk.shape[1]].astype(bool), full)
            assert np.array_equal(bits[: chunk.shape[0], g, 1, : chunk.shape[1]].astype(bool), ~part.any(axis=2))


def test_a_run_of_row_mask_bits_is_read_across_mask_words_and_segments():
    """_mask_run gives the bits from o0 on of a row mask of several words, from bit 0,
    set where they are in every segment asked for (a window across chunks takes
    each chunk's run of rows this way)."""
    rng = np.random.default_rng(6)
    masks = rng.integers(0, 2**63, (2, 3, 3, 2, 2), dtype=np.uint64) * np.uint64(2) + np.uint64(1)
    bits = np.unpackbits(masks.view(np.uint8), axis=-1, bitorder="little").reshape(2, 3, 3, 2, 128)
    for g0, g1 in ((0, 0), (1, 2), (0, 2)):
        for o0 in (0, 1, 37, 63, 64, 70, 100):
            got = int(_normals._mask_run(masks, 1, 2, g0, g1, 1, o0))
            n = min(64, 128 - o0)
            run = bits[1, 2, g0:g1 + 1, 1, o0:o0 + n].all(axis=0)
            want = sum(int(b) << q for q, b in enumerate(run))
            assert got == want, (g0, g1, o0)


def test_a_square_beams_ray_positions_are_hashes_of_seed_and_ray_id():
    """Ray i's entry point depends on (seed, i) only: a beam of fewer rays is the
    start of a longer one, and each coordinate is the documented hash."""
    from pipeline import rng as _rng
    from pipeline.rng import BEAM as BEAM_KIND

    long, short = square_beam(300, 40.0, (5.0, -2.0), seed=11), square_beam(17, 40.0, (5.0, -2.0), seed=11)
    assert np.array_equal(long.origins[:17], short.origins)
    for i in (0, 16, 299):
        u = [_rng.uniform(np.uint64(11), BEAM_KIND, i, a, 0) for a in (0, 1)]
        assert long.origins[i, 0] == 5.0 + (u[0] - 0.5) * 40.0 and long.origins[i, 2] == -2.0 + (u[1] - 0.5) * 40.0
    assert not np.array_equal(square_beam(17, 40.0, (5.0, -2.0), seed=12).origins, short.origins)


def test_a_cache_reuses_the_last_traces_buffers_but_none_of_its_voxels():
    """trace_in_voxels hands its chunk buffers to the next cache of the process (no
    page faults again); what the last trace packed there must not show through."""
    from pipeline.optics import sources

    rng = np.random.default_rng(8)
    vol1, vol2 = ((rng.random((40, 50, 70)) < p).astype(np.uint8) for p in (0.7, 0.3))
    beam = square_beam(60, 30.0, (20, 35), seed=2)
    sources._SPARE.clear()
    fresh = trace_in_voxels(ArraySource(vol2, chunks=(16, 32, 64)), beam, n_wall=N_WALL, n_poly=N_POLY)
    trace_in_voxels(ArraySource(vol1, chunks=(16, 32, 64)), beam, n_wall=N_WALL, n_poly=N_POLY)
    bits = sources._SPARE[-1][0]
    assert ChunkCache(ArraySource(vol2, chunks=(16, 16, 64)), capacity=8).bits is not bits  # other shape
    probe = ChunkCache(ArraySource(vol2, chunks=(16, 32, 64)), capacity=8)
    assert probe.bits is bits
    probe.release()
    assert sources._SPARE[-1][0] is bits
    pool = len(sources._SPARE)
    again = trace_in_voxels(ArraySource(vol2, chunks=(16, 32, 64)), beam, n_wall=N_WALL, n_poly=N_POLY)
    # Taken by the trace's cache and given back after it: had the trace made buffers of its own,
    # they would now be the newest spare (and the pool one longer, or ``bits`` dropped from it).
    assert len(sources._SPARE) == pool
    assert sources._SPARE[-1][0] is bits
    assert sum(b is bits for b, _ in sources._SPARE) == 1
    assert np.array_equal(again.exit_direction, fresh.exit_direction)
    assert np.array_equal(again.events, fresh.events)


def test_buffers_of_shorter_chunks_along_l_are_not_reused_and_the_rays_are_those_of_a_fresh_process():
    """Chunks 40 and 64 voxels long along L pack into one word a row but have 3 and 4 row-mask
    segments: a cache of 64-long chunks given the buffers of 40-long ones read masks past their
    rows (a chaotic 5 mm trace after a small volume's came out with other rays)."""
    from pipeline.optics import sources

    rng = np.random.default_rng(3)
    # Walls uniform along L, as in wood: the normals' windows skip rows by their masks.
    vol = np.repeat((rng.random((64, 70, 1)) < 0.4).astype(np.uint8), 128, axis=2)
    short = vol[:, :, :40]
    beam = square_beam(60, 12.0, (32, 56), seed=4)  # L in the fourth segment of a chunk
    fast = settings_for("fast")
    sources._SPARE.clear()
    fresh = trace_in_voxels(ArraySource(vol), beam, n_wall=N_WALL, n_poly=N_POLY, settings=fast)
    sources._SPARE.clear()
    trace_in_voxels(ArraySource(short), beam, n_wall=N_WALL, n_poly=N_POLY, settings=fast)  # chunks (64, 64, 40)
    assert sources._SPARE[-1][1].shape[2] == 3
    probe = ChunkCache(ArraySource(vol), capacity=8)
    assert probe.masks.shape[1:] == probe._masks_shape == (64, 4, 2, 1)
    probe.release()
    again = trace_in_voxels(ArraySource(vol), beam, n_wall=N_WALL, n_poly=N_POLY, settings=fast)
    assert np.array_equal(again.exit_direction, fresh.exit_direction)  # 0.46 apart with those buffers
    assert np.array_equal(again.events, fresh.events)


def test_a_process_packs_each_chunk_of_a_wood_once_and_traces_identically_from_the_memo():
    """A later trace over the same wood (a new source with the same parameters)
    copies the chunks this process packed before instead of generating them
    again, with the same rays out; other wood does not match them."""
    beam = square_beam(40, 30.0, seed=5)

    def run(seed):
        src = WoodSource(build_params("birch"), thickness_um=40.0, seed=seed, chunks=(32, 32, 32))
        res = trace_in_voxels(src, beam, n_wall=N_WALL, n_poly=N_POLY, settings=settings_for("fast"))
        return src, res

    first_src, first = run(3)
    again_src, again = run(3)
    other_src, _ = run(4)
    assert first_src.generated > 0 and first.diagnostics["chunks_loaded"] == again.diagnostics["chunks_loaded"]
    assert again_src.generated == 0
    assert other_src.generated > 0  # other wood matches none of them
    assert np.array_equal(again.exit_direction, first.exit_direction)
    assert np.array_equal(again.events, first.events) and np.array_equal(again.status, first.status)


def test_the_packed_memo_keeps_at_most_its_limit_dropping_the_least_recently_used(monkeypatch):
    from pipeline.optics.sources import PackedMemo

    bits = np.arange(4 * 8, dtype=np.uint64).reshape(4, 8)  # 64 bytes a slot
    masks = np.zeros((4, 2), np.uint64)  # 16 bytes a slot
    memo = PackedMemo(limit=3 * 80)
    for slot in range(3):
        memo.keep(("w", slot), bits, masks, slot)
    out_bits, out_masks = np.zeros_like(bits), np.zeros_like(masks)
    assert memo.fetch(("w", 0), out_bits, out_masks, 2)  # slot 0 is now the most recent
    assert np.array_equal(out_bits[2], bits[0])
    memo.keep(("w", 3), bits, masks, 3)
    assert memo.used == 3 * 80
    assert not memo.fetch(("w", 1), out_bits, out_masks, 0)  # the least recently used went
    assert all(memo.fetch(("w", k), out_bits, out_masks, 0) for k in (0, 2, 3))
    bits[3] = 7  # entries are copies
    assert memo.fetch(("w", 3), out_bits, out_masks, 1) and out_bits[1, 0] == 24
    monkeypatch.setenv("TWRAY_PACKED_MEMO_MB", "lots")
    with pytest.raises(ParameterError, match=r"`TWRAY_PACKED_MEMO_MB` must be an integer >= 0 .*'lots'"):
        PackedMemo().limit
    monkeypatch.setenv("TWRAY_PACKED_MEMO_MB", "0")
    assert PackedMemo().limit == 0


def test_bit_packed_chunks_read_back_every_voxel():
    """Chunks are held one bit per voxel in rows along L: rows of 70 voxels take
    two words, last chunks are partly filled, and voxels there read as outside."""
    vol = (np.random.default_rng(1).random((70, 33, 150)) < 0.4).astype(np.uint8)
    cache, view = resident(vol, (32, 16, 70))
    assert np.array_equal(cache.voxels((0, 0, 0), vol.shape), vol)
    assert _packing.voxel_at(*view, 70, 5, 5) == _packing.OUTSIDE  # R chunk 2 spans 64-95, the volume ends at 70
    assert _packing.voxel_at(*view, 5, 5, 150) == _packing.OUTSIDE  # L chunk 2 spans 140-209


@pytest.mark.parametrize("shape", [(16, 16, 64), (16, 9, 128), (5, 7, 136), (16, 16, 40), (7, 9, 70)])
def test_packing_64_voxels_per_compare_equals_packing_voxel_by_voxel(shape):
    """Chunks are packed from vector compares of 64 voxels: also strided views of
    a larger volume, rows that are not a multiple of 64 voxels, chunks shorter
    than the slot (the rest of the slot reads as polymer); the row masks come
    from the same pass."""
    rng = np.random.default_rng(3)
    big = (rng.random((40, 40, 300)) < 0.45).astype(np.uint8)
    big[:, ::4, :] = 1  # rows uniform over their L segments
    big[:, 1::4, 100:] = 0
    slot, n_l = (16, 16, 3), 136  # the last mask segment: 8 voxels
    for chunk in (big[: shape[0], : shape[1], : shape[2]], big[3:3 + shape[0], 5:5 + shape[1], 8:8 + shape[2]],
                  big[: shape[0], : shape[1], : 2 * shape[2] : 2], np.ones(shape, np.uint8), np.zeros(shape, np.uint8),
                  np.ones(shape, bool)):
        # Voxel by voxel: bit b of word w of row (i, j) is voxel (i, j, 64 w + b).
        ref = np.zeros(slot, np.uint64)
        for i, j, k in zip(*np.nonzero(chunk)):
            ref[i, j, k // 64] |= np.uint64(1) << np.uint64(k % 64)
        got = np.full(slot, 9, np.uint64)
        masks = np.full((slot[0], _packing.mask_segments(n_l), 2, 1), 9, np.uint64)
        assert _packing.pack_chunks(chunk, got[None], masks[None], [0], n_l)
        assert np.array_equal(got, ref)
        padded = np.zeros(slot[:2] + (n_l,), bool)
        padded[: shape[0], : shape[1], : shape[2]] = chunk
        flags = np.unpackbits(masks.view(np.uint8), axis=-1, bitorder="little").astype(bool)
        assert not flags[..., slot[1]:].any()  # no rows beyond the slot
        for g in range(_packing.mask_segments(n_l)):
            part = padded[:, :, g * _packing.MASK_SEG:(g + 1) * _packing.MASK_SEG]
            assert np.array_equal(flags[:, g, 0, : slot[1]], part.all(axis=2)), g
            assert np.array_equal(flags[:, g, 1, : slot[1]], ~part.any(axis=2)), g
    for k in range(64):  # a bad value in any byte of a row is caught
        chunk = np.zeros(shape, np.uint8)
        chunk[2, 3, k % shape[2]] = (2, 3, 128, 255)[k % 4]
        assert not _packing.pack_chunks(chunk, np.zeros((1,) + slot, np.uint64), masks[None], [0], n_l)


def test_chunks_side_by_side_along_l_are_packed_as_each_alone():
    """A run of chunks along L is packed in one pass over the volume's rows: each
    chunk lands in its own slot as if packed alone, the last one partly filled
    (its second word all padding), and the other slots are left as they were."""
    rng = np.random.default_rng(9)
    vol = (rng.random((16, 30, 278)) < 0.5).astype(np.uint8)
    vol[:, ::3, :] = 1
    slots, n_l = [5, 1, 3], 128  # chunk q (L from 128 q; the last holds 22 voxels) goes to slots[q]
    bits = np.full((6, 16, 30, 2), 9, np.uint64)
    masks = np.full((6, 16, 8, 2, 1), 9, np.uint64)
    assert _packing.pack_chunks(vol, bits, masks, slots, n_l)
    for q, s in enumerate(slots):
        alone, alone_masks = np.full((1, 16, 30, 2), 7, np.uint64), np.full((1, 16, 8, 2, 1), 7, np.uint64)
        assert _packing.pack_chunks(vol[:, :, n_l * q:n_l * (q + 1)], alone, alone_masks, [0], n_l)
        assert np.array_equal(bits[s], alone[0]) and np.array_equal(masks[s], alone_masks[0]), q
    assert np.all(bits[[0, 2, 4]] == 9) and np.all(masks[[0, 2, 4]] == 9)


def test_a_volume_with_other_values_than_0_and_1_is_refused():
    vol = np.zeros((20, 20, 20), np.uint8)
    vol[15, 3, 7] = 255
    with pytest.raises(ParameterError, match=r"0 \(polymer\) and 1 \(wall\) only, got values up to 255"):
        trace_in_voxels(ArraySource(vol, chunks=(16, 16, 16)), square_beam(20, 9.0, (10, 10), seed=1),
                   n_wall=N_WALL, n_poly=N_POLY)


@pytest.mark.parametrize("dtype", [bool, np.int16, np.float32])
def test_volumes_of_other_dtypes_trace_like_uint8(dtype):
    vol = (np.random.default_rng(2).random((40, 30, 40)) < 0.3).astype(np.uint8)
    beam = square_beam(50, 20.0, (20, 20), seed=1)
    ref = trace_in_voxels(ArraySource(vol, chunks=(16, 16, 16)), beam, n_wall=N_WALL, n_poly=N_POLY)
    got = trace_in_voxels(ArraySource(vol.astype(dtype), chunks=(16, 16, 16)), beam, n_wall=N_WALL,
                     n_poly=N_POLY)
    assert np.array_equal(got.exit_direction, ref.exit_direction)
    assert np.array_equal(got.status, ref.status)


@pytest.mark.parametrize("bad, message", [(0.5, "got the value 0.5"), (-1, "got the value -1"),
                                          (3, "got values up to 3")])
def test_a_volume_value_that_is_neither_0_nor_1_is_named(bad, message):
    vol = np.zeros((20, 20, 20), np.float32 if bad == 0.5 else np.int16)
    vol[4, 3, 7] = bad
    with pytest.raises(ParameterError, match=message):
        trace_in_voxels(ArraySource(vol, chunks=(16, 16, 16)), square_beam(20, 9.0, (10, 10), seed=1),
                   n_wall=N_WALL, n_poly=N_POLY)


def test_the_normal_window_is_the_same_whatever_the_chunking():
    """smoothed_wall reads a window inside one chunk by a shorter path than one
    across chunks or clamped at the faces; both must give the same numbers, bit for bit."""
    rng = np.random.default_rng(4)
    vol = (ndimage.gaussian_filter(rng.random((48, 100, 48)), 2.0) > 0.5).astype(np.uint8)
    # One chunk (row masks of two words along T: windows across T = 64 read both),
    # chunks across the window (whose rows the masks of every chunk they cross
    # settle, also masks of two words), and row masks saying nothing (every row is read).
    views = [window_view(*resident(vol, chunks))
             for chunks in [(48, 100, 48), (16, 24, 20), (20, 13, 64), (16, 100, 20)]]
    views.append(window_view(*resident(vol, (48, 100, 48)), masks=np.zeros((1, 48, 3, 2, 2), np.uint64)))
    scratch = _normals.window_scratch(5.25)
    pts = np.column_stack([rng.uniform(-2, 50, 400), rng.uniform(-2, 102, 400), rng.uniform(-2, 50, 400)])
    for x in pts:
        out = []
        for view in views:
            g, h = np.empty(3), np.empty(6)
            s = _normals.smoothed_wall(*view, x, 1.75, 5.25, g, h, *scratch)
            out.append(np.concatenate([[s], g, h]))
        assert all(np.array_equal(out[0], o) for o in out[1:]), x


def test_chunk_sets_of_live_rays_are_exact():
    from pipeline.optics.voxels import _chunks_of_boxes, _unique_rows

    rng = np.random.default_rng(0)
    for spread in [5] * 50 + [3000] * 5:  # boxes close together (a grid of them) or far apart
        lo = rng.integers(-spread, spread, (rng.integers(1, 40), 3))
        hi = lo + rng.integers(0, 3, lo.shape)
        want = {(a, b, c) for (l0, l1, l2), (h0, h1, h2) in zip(lo.tolist(), hi.tolist())
                for a in range(l0, h0 + 1) for b in range(max(l1, 0), h1 + 1) for c in range(l2, h2 + 1)}
        got = _chunks_of_boxes(lo, hi)
        assert np.array_equal(got, np.array(sorted(want), np.int64).reshape(-1, 3))
        assert np.array_equal(_unique_rows(lo), np.unique(lo, axis=0))


@pytest.mark.parametrize("refine", [0, 9, 1.5, True, "2"])
def test_refine_is_an_integer_from_1_to_8(refine):
    with pytest.raises(ParameterError, match="`refine` must be an integer in \\[1, 8\\]"):
        settings_for("accurate", refine=refine)
    assert settings_for("accurate").refine == 2 and settings_for("fast").refine == 1


@pytest.mark.parametrize("change, message", [
    ({"refit": 4}, r"`refit` must be in \[0, newton = 3\], got 4"),
    ({"radius_vox": 30.0}, r"`radius_vox` in \[1, 24\], got 1.75, 30.0"),
])
def test_trace_settings_refuse_impossible_normal_windows(change, message):
    with pytest.raises(ParameterError, match=message):
        settings_for("fast", **change)


def test_smoothed_wall_gradient_and_hessian_are_the_derivatives_of_S():
    """The normal's ∇S and the Hessian its Newton model steps on are the exact
    derivatives of the windowed S (central differences, windows across chunks)."""
    rng = np.random.default_rng(3)
    vol = (ndimage.gaussian_filter(rng.random((40, 40, 40)), 2.5) > 0.5).astype(np.uint8)
    view = window_view(*resident(vol, (16, 24, 20)))
    scratch = _normals.window_scratch(6.0)

    def S(x):
        g, h = np.empty(3), np.empty(6)
        s = _normals.smoothed_wall(*view, np.asarray(x, np.float64), 2.0, 6.0, g, h, *scratch)
        H = np.array([[h[0], h[3], h[4]], [h[3], h[1], h[5]], [h[4], h[5], h[2]]])
        return s, g.copy(), H

    e, checked = 1e-5, 0
    for x in rng.uniform(12, 28, size=(12, 3)):
        x = np.floor(x) + 0.3  # window bounds and weight cut-offs move at fractions 0.5
        s, g, H = S(x)
        assert 0.02 < s < 0.98 or not np.any(g)
        fd_g = [(S(x + e * d)[0] - S(x - e * d)[0]) / (2 * e) for d in np.eye(3)]
        fd_H = np.array([(S(x + e * d)[1] - S(x - e * d)[1]) / (2 * e) for d in np.eye(3)])
        assert np.allclose(g, fd_g, atol=1e-7)
        assert np.allclose(H, fd_H, atol=1e-6)
        checked += np.linalg.norm(g) > 0.01
    assert checked >= 4  # most points see both phases
