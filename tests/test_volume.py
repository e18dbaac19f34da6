"""Lazy chunked volumes: chunk-shape, order and worker independence; laziness; metadata."""

import json

import numpy as np
import pytest
import zarr

from pipeline.microstructure.export import write_tiff_stack
from pipeline.microstructure.model import generate_block
from pipeline.microstructure.volume import NOT_GENERATED, WoodVolume
from pipeline.params import build_params, make_grid

SIZE = (40.0, 30.0, 35.0)  # µm → (80, 60, 70) voxels


@pytest.fixture(scope="module")
def params():
    return build_params("birch")


@pytest.fixture(scope="module")
def reference(params):
    grid = make_grid(SIZE, 0.5, (3.0, -7.0, 11.0), params)
    return generate_block(params, grid, (0, 0, 0), grid.shape, seed=21)


def make(tmp_path, params, name, chunks, origin=(3.0, -7.0, 11.0), size=SIZE):
    grid = make_grid(size, 0.5, origin, params)
    return WoodVolume.create(tmp_path / name, params, grid, seed=21, chunks=chunks)


def test_chunk_shapes_and_generation_order_do_not_change_the_voxels(tmp_path, params, reference):
    a = make(tmp_path, params, "a.zarr", (32, 32, 32))
    b = make(tmp_path, params, "b.zarr", (17, 60, 9))
    a.generate(scheduler="sync")
    for idx in reversed(b.all_chunks()):  # the opposite order, one chunk at a time
        b.ensure_chunk(idx)
    assert np.array_equal(a[:, :, :], reference)
    assert np.array_equal(b[:, :, :], reference)
    # Chunk files are written directly (zarr reads them above), edge chunks padded;
    # an edge chunk read back from its file is cut to the volume.
    assert a._files is not None and b._files is not None
    assert np.array_equal(b.ensure_chunk((4, 0, 7)), reference[68:80, 0:60, 63:70])


@pytest.mark.parametrize("n_workers", [1, 2])
def test_dask_workers_give_identical_volumes(tmp_path, params, reference, n_workers):
    from distributed import Client, LocalCluster

    vol = make(tmp_path, params, f"w{n_workers}.zarr", (24, 32, 20))
    with LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster, Client(cluster) as client:
        n = vol.generate(scheduler=client)
        assert len(client.scheduler_info()["workers"]) == n_workers
    assert n == len(vol.all_chunks())
    assert vol.generated_chunks() == set(vol.all_chunks())
    assert np.array_equal(WoodVolume.open(vol.path)[:, :, :], reference)


def test_reading_one_chunk_of_a_large_volume_generates_only_that_chunk(tmp_path, params):
    vol = make(tmp_path, params, "big.zarr", (128, 128, 128), origin=(0, 0, 0),
               size=(1500.0, 1500.0, 1500.0))
    assert vol.shape == (3000, 3000, 3000)
    assert len(vol.all_chunks()) == 24**3
    region = vol[1300:1330, 260:300, 2600:2610]
    assert vol.generated_chunks() == {(10, 2, 20)}
    assert region.shape == (30, 40, 10) and set(np.unique(region)) <= {0, 1}
    # The same voxels as a direct evaluation of the model there.
    direct = generate_block(params, vol.grid, (1300, 260, 2600), (30, 40, 10), seed=21)
    assert np.array_equal(region, direct)
    # A second read is served from the store: nothing new is generated.
    vol[1290:1300, 256:260, 2560:2570]
    assert vol.generated_chunks() == {(10, 2, 20)}


def test_unread_chunks_hold_the_sentinel_and_reopen_keeps_parameters(tmp_path, params):
    vol = make(tmp_path, params, "lazy.zarr", (40, 30, 35))
    raw = zarr.open_array(vol.path / "0", mode="r")
    assert np.all(raw[:40, :30, :35] == NOT_GENERATED)
    again = WoodVolume.open(vol.path)
    assert again.params == params and again.seed == 21 and again.grid.origin_um == (3.0, -7.0, 11.0)
    assert set(np.unique(again[:40, :30, :35])) <= {0, 1}


def test_ome_zarr_metadata_names_axes_and_voxel_size_in_micrometers(tmp_path, params):
    vol = make(tmp_path, params, "ome.zarr", (32, 32, 32))
    meta = json.loads((vol.path / "zarr.json").read_text())["attributes"]
    ome = meta["ome"]
    assert ome["version"] == "0.5"
    ms = ome["multiscales"][0]
    assert [a["name"] for a in ms["axes"]] == ["r", "t", "l"]
    assert {a["unit"] for a in ms["axes"]} == {"micrometer"}
    scale, translation = ms["datasets"][0]["coordinateTransformations"]
    assert scale == {"type": "scale", "scale": [0.5, 0.5, 0.5]}
    assert translation["translation"] == [3.0, -7.0, 11.0]
    arr = json.loads((vol.path / "0" / "zarr.json").read_text())
    assert arr["dimension_names"] == ["r", "t", "l"]
    assert arr["zarr_format"] == 3
    assert meta["twray"]["params"]["wall_thickness_um"] == 2.0


def test_tiff_export_writes_one_slice_per_L_with_the_voxels(tmp_path, params, reference):
    import tifffile

    vol = make(tmp_path, params, "t.zarr", (32, 32, 32))
    paths = write_tiff_stack(vol, tmp_path / "tiff")
    assert len(paths) == vol.shape[2]
    stack = np.stack([tifffile.imread(p) for p in paths], axis=-1)
    assert np.array_equal(stack, reference)
    with tifffile.TiffFile(paths[0]) as tif:
        assert tif.imagej_metadata["unit"] == "um"
