"""The command line: the generate contract, slices, and bad input (one line, exit 2, nothing written)."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from pipeline.cli import main
from pipeline.microstructure.volume import WoodVolume
from pipeline.optics.rays import VOXEL_COUNTS

# What only a voxel method prints (a surface medium reads no voxels).
VOXEL_ONLY = ("voxels_generated", "chunks_loaded", "traced_voxel_um", "refine") + VOXEL_COUNTS


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_generate_writes_a_volume_and_slices(tmp_path, capsys):
    out = tmp_path / "v.zarr"
    code, stdout, _ = run(capsys, "generate", "--preset", "birch", "--size-um", "30,25,20",
                          "--chunks", "32,32,16", "--seed", "3", "--set", "vessels=false",
                          "--out", str(out))
    assert code == 0, stdout
    vol = WoodVolume.open(out)
    assert vol.shape == (60, 50, 40) and vol.chunks == (32, 32, 16)
    assert vol.generated_chunks() == set(vol.all_chunks())
    assert not vol.params.vessels and vol.seed == 3
    assert "wall fraction" in stdout
    code, stdout, _ = run(capsys, "slices", str(out), "--out", str(tmp_path / "png"))
    assert code == 0
    for name in ("slice_RT.png", "slice_LT.png", "slice_LR.png", "slices.png"):
        assert (tmp_path / "png" / name).stat().st_size > 0


def test_lazy_generate_writes_metadata_only(tmp_path, capsys):
    out = tmp_path / "lazy.zarr"
    code, stdout, _ = run(capsys, "generate", "--size-um", "1500,1500,1500", "--lazy",
                          "--out", str(out))
    assert code == 0 and "lazy" in stdout
    assert WoodVolume.open(out).generated_chunks() == set()


def test_config_file_and_set_overrides(tmp_path, capsys):
    cfg = tmp_path / "wood.yaml"
    cfg.write_text("preset: birch\nwall_thickness_um: 3.0\nray_cells: false\n")
    out = tmp_path / "c.zarr"
    code, _, err = run(capsys, "generate", "--config", str(cfg), "--set", "fibre_diameter_um=20",
                       "--size-um", "10,10,10", "--out", str(out))
    assert code == 0, err
    p = WoodVolume.open(out).params
    assert (p.wall_thickness_um, p.ray_cells, p.fibre_diameter_um) == (3.0, False, 20.0)


def test_laminate_notation_on_the_command_line(tmp_path, capsys):
    out = tmp_path / "lam.zarr"
    code, _, err = run(capsys, "generate", "--set", "laminate=[0/-45/90/45/0]", "--size-um",
                       "10,10,10", "--out", str(out))
    assert code == 0, err
    assert WoodVolume.open(out).params.laminate == (0.0, -45.0, 90.0, 45.0, 0.0)


BAD = [
    (["--set", "wall_thickness_um=-2"], "wall_thickness_um", "> 0"),
    (["--set", "wall_thickness_um=15"], "wall_thickness_um", "keeps a lumen"),
    (["--set", "wall_thickness_um=20", "--set", "fibre_diameter_um=14.5"], "wall_thickness_um", "<"),
    (["--preset", "oak"], "preset", "birch"),
    (["--set", "wall_thicknes_um=2"], "wall_thicknes_um", "unknown parameter"),
    (["--set", "wall_thickness_um=thick"], "wall_thickness_um", "must be a number"),
    (["--set", "vessels=maybe"], "vessels", "true or false"),
    (["--set", "ray_seriate=2.5"], "ray_seriate", "integer"),
    (["--set", "vessel_pair_fraction=1.5"], "vessel_pair_fraction", "probability"),
    (["--set", "laminate=[0/abc/90]"], "laminate", "[0/-45/90/45/0]"),
    (["--size-um", "0,150,100"], "size_um", "> 0"),
    (["--size-um", "150,150"], "size_um", "three"),
    (["--voxel-um", "1.5"], "voxel_um", "wall_thickness_um/2"),
    (["--voxel-um", "-0.5"], "voxel_um", ">= 0.01"),
    (["--seed", "-1"], "seed", ">= 0"),
    (["--seed", "one"], "seed", "integer"),
    (["--chunks", "0,64,64"], "chunks", "> 0"),
    (["--origin-um", "a,b,c"], "origin_um", "numbers"),
    (["--set", "fibre_diameter_um"], "--set", "key=value"),
    (["--set", "node_jitter=0.3"], "node_jitter", "in [0, 0.2]"),
    (["--set", "fibre_tip_um=-1"], "fibre_tip_um", "in [0, fibre_length_um/2"),
    (["--set", "fibre_tip_um=700"], "fibre_tip_um", "two tips fit"),
    (["--set", "fibre_tip_um=100", "--set", "end_plates=false"], "fibre_tip_um", "end_plates is false"),
    (["--preset", "balsa", "--set", "fibre_tip_um=100"], "fibre_tip_um", "cell_shape polygon"),
    (["--voxel-um", "nan"], "voxel_um", "finite"),
    (["--voxel-um", "1e-6"], "voxel_um", ">= 0.01 µm"),
    (["--size-um", "1e6,1e6,1e6"], "size_um", "at most 1e13 voxels"),
    (["--size-um", "10000000,150,100"], "generate", "add --yes (with make: YES=1) to run it"),  # a 10 m sample: 22 CPU-h
]


@pytest.mark.parametrize("extra, field, rule", BAD, ids=[b[1] + "-" + str(i) for i, b in enumerate(BAD)])
def test_bad_input_one_line_exit_2_nothing_written(tmp_path, capsys, extra, field, rule):
    out = tmp_path / "bad.zarr"
    argv = ["generate", "--size-um", "150,150,100", "--out", str(out)]
    # a later --size-um wins in argparse, so the bad one can simply be appended
    code, stdout, err = run(capsys, *(argv + extra))
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("twray: error:")
    assert field in lines[0] and rule in lines[0], lines[0]
    assert list(tmp_path.iterdir()) == []  # no store, no partial store


def test_bad_yaml_config_names_file_line_and_field(tmp_path, capsys):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("wall_thickness_um: 2.0\nvesels: false\n")
    code, _, err = run(capsys, "generate", "--config", str(cfg), "--size-um", "10,10,10",
                       "--out", str(tmp_path / "x.zarr"))
    assert code == 2
    assert "bad.yaml line 2" in err and "`vesels`" in err
    assert not (tmp_path / "x.zarr").exists()


def test_existing_output_is_not_overwritten_without_flag(tmp_path, capsys):
    out = tmp_path / "v.zarr"
    assert run(capsys, "generate", "--size-um", "5,5,5", "--out", str(out))[0] == 0
    before = WoodVolume.open(out)[:, :, :]
    code, _, err = run(capsys, "generate", "--size-um", "5,5,5", "--seed", "9", "--out", str(out))
    assert code == 2 and "--overwrite" in err
    assert np.array_equal(WoodVolume.open(out)[:, :, :], before)


def test_overwrite_replaces_a_volume_twray_wrote_and_nothing_else(tmp_path, capsys):
    out = tmp_path / "v.zarr"
    assert run(capsys, "generate", "--size-um", "5,5,5", "--out", str(out))[0] == 0
    before = WoodVolume.open(out)[:, :, :]
    assert run(capsys, "generate", "--size-um", "5,5,5", "--seed", "9", "--out", str(out), "--overwrite")[0] == 0
    assert not np.array_equal(WoodVolume.open(out)[:, :, :], before)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.zarr"]  # nothing staged or set aside is left
    # A folder, a file, or a Zarr store that twray did not write is never deleted.
    folder = tmp_path / "thesis"
    folder.mkdir()
    (folder / "chapter1.tex").write_text("precious")
    plain = tmp_path / "notes.txt"
    plain.write_text("precious")
    other = tmp_path / "other.zarr"
    other.mkdir()
    (other / "zarr.json").write_text('{"zarr_format": 3, "node_type": "group", "attributes": {"x": 1}}')
    for victim in (folder, plain, other):
        code, _, err = run(capsys, "generate", "--size-um", "5,5,5", "--out", str(victim), "--overwrite")
        assert code == 2 and "not a store twray wrote" in err and err.count("\n") == 1
    assert (folder / "chapter1.tex").read_text() == "precious" and plain.read_text() == "precious"
    assert (other / "zarr.json").exists()
    with pytest.raises(Exception, match="not a store twray wrote"):
        WoodVolume.create(folder, WoodVolume.open(out).params, WoodVolume.open(out).grid, seed=1,
                          overwrite=True)
    assert (folder / "chapter1.tex").exists()


def test_trace_out_replaces_its_own_result_but_no_other_file(tmp_path, capsys):
    argv = ["trace", "--preset", "birch", "--thickness-mm", "0.02", "--delta-ri", "0.01", "--rays", "10",
            "--beam-um", "10", "--method", "fast"]
    for name in ("r.nc", "r.zarr"):
        out = tmp_path / name
        assert run(capsys, *argv, "--out", str(out))[0] == 0
        assert run(capsys, *argv, "--seed", "2", "--out", str(out))[0] == 0  # its own: replaced
    precious = tmp_path / "data.nc"
    precious.write_bytes(b"not twray's")
    folder = tmp_path / "folder.zarr"
    folder.mkdir()
    (folder / "keep.txt").write_text("precious")
    for victim in (precious, folder):
        code, _, err = run(capsys, *argv, "--out", str(victim))
        assert code == 2 and "not a" in err and "twray wrote" in err
    assert precious.read_bytes() == b"not twray's" and (folder / "keep.txt").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data.nc", "folder.zarr", "r.nc", "r.zarr"]


def test_failure_during_generation_leaves_nothing(tmp_path, capsys, monkeypatch):
    from pipeline.microstructure import volume

    def boom(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(volume, "generate_block", boom)
    out = tmp_path / "v.zarr"
    monkeypatch.setenv("TMPDIR", str(tmp_path.parent / f"{tmp_path.name}-tmp"))  # where a cacheless log goes
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", None)
    assert main(["generate", "--size-um", "5,5,5", "--out", str(out)]) == 1
    assert list(tmp_path.iterdir()) == []
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "internal error, RuntimeError: disk full" in err
    log = err.split("traceback in ")[-1].rstrip(")")
    assert "raise RuntimeError(\"disk full\")" in open(log).read()  # the whole traceback is in the log


def test_console_script_exit_code_is_2_for_bad_input(tmp_path):
    res = subprocess.run([sys.executable, "-m", "pipeline", "generate", "--size-um", "1,1,1",
                          "--set", "wall_thickness_um=0", "--out", str(tmp_path / "v.zarr")],
                         capture_output=True, text=True)
    assert res.returncode == 2
    assert res.stderr.count("\n") == 1 and "wall_thickness_um" in res.stderr


def test_trace_json_on_lazily_generated_wood(tmp_path, capsys):
    import json

    import xarray as xr

    out = tmp_path / "rays.nc"
    code, stdout, err = run(capsys, "trace", "--preset", "birch", "--thickness-mm", "0.05",
                            "--delta-ri", "0.01", "--rays", "60", "--beam-um", "40",
                            "--method", "fast", "--json", "--out", str(out))
    assert code == 0, err
    s = json.loads(stdout)
    for key in ("fwhm_r_deg", "fwhm_l_deg", "haze", "n_rays", "n_transmitted", "n_lost", "method"):
        assert key in s
    assert s["n_rays"] == 60 and s["n_transmitted"] + s["n_lost"] == 60 and s["method"] == "fast"
    # Walls run along L: light spreads in the R-T plane far more than in L-T.
    assert s["fwhm_r_deg"] > 3 * s["fwhm_l_deg"]
    ds = xr.open_dataset(out)
    assert ds.sizes["ray"] == 60 and ds["theta_r"].attrs["units"] == "degree"
    ds.close()


def test_trace_user_volume_npy_index_matched(tmp_path, capsys):
    import json

    vol = np.zeros((40, 30, 40), np.uint8)
    vol[:, 10:14, :] = 1
    np.save(tmp_path / "v.npy", vol)
    code, stdout, err = run(capsys, "trace", "--volume", str(tmp_path / "v.npy"), "--delta-ri", "0",
                            "--rays", "50", "--beam-um", "10", "--json")
    assert code == 0, err
    s = json.loads(stdout)
    assert s["n_transmitted"] == 50 and s["fwhm_r_deg"] == 0.0 and s["haze"] == 0.0
    assert s["interfaces_per_ray"] == 2.0 and s["method"] == "accurate"  # a scan's default: it has voxels only


def test_a_user_volume_is_traced_on_its_own_voxels(tmp_path, capsys):
    import json

    vol = np.zeros((40, 30, 40), np.uint8)
    vol[:, 10:14, :] = 1
    np.save(tmp_path / "v.npy", vol)
    code, stdout, err = run(capsys, "trace", "--volume", str(tmp_path / "v.npy"), "--delta-ri", "0.01",
                            "--rays", "20", "--beam-um", "10", "--method", "accurate", "--json")
    assert code == 0, err
    s = json.loads(stdout)
    assert s["refine"] == 1 and s["traced_voxel_um"] == 0.5  # accurate's refine needs a model
    code, _, err = run(capsys, "trace", "--volume", str(tmp_path / "v.npy"), "--delta-ri", "0.01",
                       "--refine", "2")
    assert code == 2 and "`refine` applies to generated wood" in err and err.count("\n") == 1


def test_trace_oblique_beam_from_air_with_negative_angles(tmp_path, capsys):
    """`--incidence-deg -10,5` (negative values read as values, as `--delta-ri -1e-3` is):
    through an index-matched sample every ray leaves into air at exactly those angles."""
    import json

    import xarray as xr

    vol = np.zeros((60, 20, 60), np.uint8)
    vol[:, 5:9, :] = 1
    np.save(tmp_path / "v.npy", vol)
    code, stdout, err = run(capsys, "trace", "--volume", str(tmp_path / "v.npy"), "--delta-ri", "-0e-3",
                            "--incidence-deg", "-10,5", "--exit", "air", "--rays", "40", "--beam-um", "8",
                            "--json", "--out", str(tmp_path / "r.nc"))
    assert code == 0, err
    s = json.loads(stdout)
    assert s["incidence_deg"] == [-10.0, 5.0] and s["delta_ri"] == 0.0
    assert s["n_transmitted"] == 40 and s["haze"] == 0.0 and s["fwhm_r_deg"] == 0.0
    with xr.open_dataset(tmp_path / "r.nc") as ds:
        assert np.allclose(ds["theta_r"], -10.0, atol=1e-12) and np.allclose(ds["theta_l"], 5.0, atol=1e-12)
    code, stdout, err = run(capsys, "trace", "--volume", str(tmp_path / "v.npy"), "--delta-ri", "-1e-3",
                            "--rays", "5", "--beam-um", "8", "--json")
    assert code == 0, err
    assert json.loads(stdout)["delta_ri"] == -1e-3


@pytest.mark.parametrize("extra, field", [
    (["--method", "magic"], "method"),
    (["--delta-ri", "big"], "delta_ri"),
    (["--rays", "0"], "rays"),
    (["--method", "paper", "--step-vox", "5"], "step_vox"),
    (["--exit", "water"], "exit"),
    (["--incidence-deg", "95,0"], "incidence_deg"),
    (["--incidence-deg", "5"], "incidence_deg"),
    (["--incidence-deg", "-5,x"], "incidence_deg"),
    (["--refine", "0"], "refine"),
    (["--refine", "12"], "refine"),
    # NaN and inf are refused wherever a number is read
    (["--delta-ri", "nan"], "delta_ri"),
    (["--beam-um", "inf"], "beam_um"),
    (["--thickness-mm", "nan"], "thickness_mm"),
    (["--incidence-deg", "nan,0"], "incidence_deg"),
    # absurd sizes are refused before any work, with the estimate and what would make them fit
    (["--rays", "1000000000000"], "more memory than this machine's"),
    (["--beam-um", "1e9"], "a narrower beam (--beam-um)"),
    (["--thickness-mm", "10000"], "a thinner sample"),
])
def test_trace_bad_input(tmp_path, tmp_path_factory, monkeypatch, capsys, extra, field):
    # As on a first run of these sources, whose refusal also says it would compile the kernels first:
    # still one line.
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path_factory.mktemp("kernels")))
    argv = ["trace", "--preset", "birch", "--thickness-mm", "0.05", "--delta-ri", "0.01",
            "--out", str(tmp_path / "r.nc")] + extra
    code, _, err = run(capsys, *argv)
    assert code == 2 and field in err and err.count("\n") == 1
    assert list(tmp_path.iterdir()) == []


def test_outputs_that_cannot_be_written_are_refused_before_any_work(tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    trace = ["trace", "--preset", "birch", "--thickness-mm", "0.05", "--delta-ri", "0.01", "--rays", "5"]
    for out, rule in (("", "must be a path"), (str(tmp_path / "afile" / "r.nc"), "is a file")):
        code, _, err = run(capsys, *trace, "--out", out)
        assert code == 2 and rule in err and err.count("\n") == 1, err
        code, _, err = run(capsys, "generate", "--size-um", "10,10,10", "--out", out)
        assert code == 2 and rule in err and err.count("\n") == 1, err
    code, _, err = run(capsys, "study", str(tmp_path / "afile"), "--results", str(tmp_path / "afile"))
    assert code == 2 and "`results` must be a folder" in err
    (tmp_path / "bin.yaml").write_bytes(b"\x00\x01\xff\xfe")
    code, _, err = run(capsys, "study", str(tmp_path / "bin.yaml"), "--results", str(tmp_path / "r"))
    assert code == 2 and "must be a UTF-8 text file of YAML" in err and err.count("\n") == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "bin.yaml"]


def test_a_beam_wider_than_the_volume_is_refused_and_an_empty_one_traces_clean(tmp_path, capsys):
    vol = np.zeros((40, 20, 40), np.uint8)  # all polymer: nothing scatters
    np.save(tmp_path / "v.npy", vol)
    base = ["trace", "--volume", str(tmp_path / "v.npy"), "--delta-ri", "0.01", "--rays", "20", "--json"]
    code, _, err = run(capsys, *base, "--beam-um", "30")  # the volume is 20 µm wide at 0.5 µm
    assert code == 2 and "`beam_um` must fit the volume's R-L face (20 x 20 µm)" in err
    code, out, err = run(capsys, *base, "--beam-um", "10")
    assert code == 0 and err == "", err  # no warning, no division by zero
    s = json.loads(out)
    assert s["fwhm_r_deg"] == 0.0 and s["haze"] == 0.0 and s["n_transmitted"] == 20


def test_a_long_run_asks_for_yes_above_the_configured_cpu_hours(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("TWRAY_CONFIRM_CPU_HOURS", "0.001")
    argv = ["generate", "--size-um", "300,300,300", "--out", str(tmp_path / "v.zarr")]
    code, _, err = run(capsys, *argv)
    assert code == 2 and "add --yes (with make: YES=1) to run it" in err and "CPU" in err and "use --lazy" in err
    assert list(tmp_path.iterdir()) == []
    code, _, _ = run(capsys, *argv, "--lazy")  # nothing generated: nothing to ask
    assert code == 0
    monkeypatch.setenv("TWRAY_CONFIRM_CPU_HOURS", "lots")
    code, _, err = run(capsys, *argv[:-1], str(tmp_path / "w.zarr"), "--lazy")
    assert code == 2 and "TWRAY_CONFIRM_CPU_HOURS" in err


def test_ctrl_c_is_one_line_exit_130_and_leaves_nothing(tmp_path):
    import signal
    import time

    # As a terminal's Ctrl-C reaches a foreground command: a test run started in the background
    # of a shell (`make test &`) ignores SIGINT, and its children would inherit that.
    proc = subprocess.Popen([sys.executable, "-m", "pipeline", "generate", "--size-um", "1000,1000,1000",
                             "--out", str(tmp_path / "v.zarr"), "--yes"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not any(p.name.startswith(".v.zarr.partial") for p in tmp_path.iterdir()):
        time.sleep(0.2)
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("twray: interrupted"), err
    assert list(tmp_path.iterdir()) == []


def test_a_lazy_volume_traces_as_its_generated_twin_and_an_empty_one_is_refused(tmp_path, capsys):
    for name, lazy in (("lazy.zarr", ["--lazy"]), ("full.zarr", [])):
        code, _, err = run(capsys, "generate", "--size-um", "20,15,20", "--seed", "2", "--out",
                           str(tmp_path / name), *lazy)
        assert code == 0, err
    results = []
    for name in ("lazy.zarr", "full.zarr"):
        code, out, err = run(capsys, "trace", "--volume", str(tmp_path / name), "--delta-ri", "0.02",
                             "--rays", "30", "--beam-um", "8", "--json")
        assert code == 0, err
        s = json.loads(out)
        results.append((s["fwhm_r_deg"], s["haze"], s["interfaces_per_ray"]))
    assert results[0] == results[1] and results[0][2] > 0
    np.save(tmp_path / "flat.npy", np.zeros((20, 0, 20), np.uint8))
    code, _, err = run(capsys, "trace", "--volume", str(tmp_path / "flat.npy"), "--delta-ri", "0.01",
                       "--rays", "5", "--beam-um", "2")
    assert code == 2 and "at least one voxel along R, T and L" in err and err.count("\n") == 1


def test_export_tiff_of_a_volume_larger_than_the_disk_is_refused_before_writing(tmp_path, capsys):
    code, _, err = run(capsys, "generate", "--size-um", "1500,1500,500000", "--lazy", "--out",
                       str(tmp_path / "huge.zarr"))  # 9e12 voxels: 9 TB of TIFF
    assert code == 0, err
    code, _, err = run(capsys, "export-tiff", str(tmp_path / "huge.zarr"), "--out", str(tmp_path / "tif"))
    assert code == 2 and "more disk than the" in err and err.count("\n") == 1, err
    assert not (tmp_path / "tif").exists()


def test_materialise_generates_a_lazy_store_in_place_and_equals_an_eager_one(tmp_path, capsys):
    import zarr

    common = ["generate", "--size-um", "40,30,40", "--chunks", "32,32,32", "--seed", "4"]
    assert run(capsys, *common, "--lazy", "--out", str(tmp_path / "lazy.zarr"))[0] == 0
    assert run(capsys, *common, "--out", str(tmp_path / "eager.zarr"))[0] == 0
    raw = zarr.open_array(tmp_path / "lazy.zarr" / "0", mode="r")
    assert np.all(raw[:] == 255)  # outside twray, a lazy store reads as 255 until generated
    code, out, err = run(capsys, "generate", "--materialise", "--out", str(tmp_path / "lazy.zarr"))
    assert code == 0 and "18 chunks generated" in out, err
    assert np.array_equal(raw[:], zarr.open_array(tmp_path / "eager.zarr" / "0", mode="r")[:])
    code, _, err = run(capsys, "generate", "--materialise", "--size-um", "1,1,1", "--out", str(tmp_path / "x"))
    assert code == 2 and "--materialise" in err


def test_large_volumes_get_an_ome_zarr_pyramid_that_viewers_open_coarse_first(tmp_path, capsys):
    import json

    import zarr

    out = tmp_path / "long.zarr"  # 600 voxels along R: above the 512 of the top level
    assert run(capsys, "generate", "--size-um", "300,20,20", "--chunks", "128,40,40", "--out", str(out))[0] == 0
    ms = json.loads((out / "zarr.json").read_text())["attributes"]["ome"]["multiscales"][0]
    assert [d["path"] for d in ms["datasets"]] == ["0", "1"]
    assert ms["datasets"][1]["coordinateTransformations"][0]["scale"] == [1.0, 1.0, 1.0]
    full, coarse = zarr.open_array(out / "0")[:], zarr.open_array(out / "1")[:]
    assert coarse.shape == (300, 20, 20) and np.array_equal(coarse, full[::2, ::2, ::2])
    assert WoodVolume.open(out).shape == (600, 40, 40)
    small = tmp_path / "small.zarr"
    assert run(capsys, "generate", "--size-um", "20,20,20", "--out", str(small))[0] == 0
    ms = json.loads((small / "zarr.json").read_text())["attributes"]["ome"]["multiscales"][0]
    assert [d["path"] for d in ms["datasets"]] == ["0"] and not (small / "1").exists()


def test_trace_exact_on_generated_wood_reads_no_voxels_and_a_volume_is_refused(tmp_path, capsys):
    import json

    code, stdout, err = run(capsys, "trace", "--preset", "birch", "--thickness-mm", "0.05", "--delta-ri", "0.01",
                            "--rays", "40", "--beam-um", "40", "--json")  # exact: the default for generated wood
    assert code == 0, err
    s = json.loads(stdout)
    assert s["method"] == "exact" and s["n_transmitted"] + s["n_lost"] == 40
    # A surface medium reads no voxels: no voxel method's diagnostics are printed for it.
    assert not set(s) & set(VOXEL_ONLY), sorted(set(s) & set(VOXEL_ONLY))
    assert s["fwhm_r_deg"] > 3 * s["fwhm_l_deg"]
    vol = tmp_path / "v.npy"
    np.save(vol, np.zeros((20, 20, 20), np.uint8))
    code, _, err = run(capsys, "trace", "--volume", str(vol), "--method", "exact", "--rays", "5", "--beam-um", "2",
                       "--delta-ri", "0.01")
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "--volume has voxels only: use --method iso" in err and "accurate" in err


def test_trace_a_reference_lattice_by_name_with_exact_and_with_a_voxel_method(tmp_path, capsys):
    """``--reference`` traces a lattice of exact optics: ``exact`` gives what the independent exact
    tracer gives on the same beam; a voxel method traces the lattice's voxelisation."""
    from pipeline.summary import summarize
    from pipeline.optics.lattice import tube_lattice
    from pipeline.optics.rays import square_beam
    from pipeline.optics.settings import Optics, settings_for
    from pipeline.optics.trace import trace

    args = ["trace", "--reference", "tubes-square", "--pitch-um", "14.5", "--wall-um", "2", "--jitter", "0.1",
            "--thickness-mm", "0.04", "--delta-ri", "0.03", "--rays", "300", "--beam-um", "80", "--seed", "4",
            "--json"]
    lat = tube_lattice(14.5, 7.25, 2.0, jitter=0.1, seed=4)
    beam = square_beam(300, 80.0, seed=4)
    code, stdout, err = run(capsys, *args, "--method", "exact", "--out", str(tmp_path / "r.nc"))
    assert code == 0, err
    s = json.loads(stdout)
    ref = summarize(lat.trace_independently(beam.origins, beam.unit_directions(), n_wall=1.52, n_poly=1.49, thickness_um=40.0),
                    seed=4)
    assert s["method"] == "exact" and not set(s) & set(VOXEL_ONLY) and s["n_rays"] == 300
    for k in ("fwhm_r_deg", "haze", "n_transmitted"):
        assert s[k] == pytest.approx(ref[k], rel=1e-6), k
    assert s["fwhm_r_deg"] > 1.0
    import xarray as xr

    with xr.open_dataset(tmp_path / "r.nc") as ds:
        assert json.loads(ds.attrs["inputs"])["reference"]["name"] == "tubes-square"
    code, stdout, err = run(capsys, *args, "--method", "fast", "--voxel-um", "0.5")
    assert code == 0, err
    voxels = trace(lat.source(thickness_um=40.0, voxel_um=0.5), beam, Optics(1.52, 1.49), settings_for("fast"))
    assert json.loads(stdout)["fwhm_r_deg"] == summarize(voxels, seed=4)["fwhm_r_deg"]


@pytest.mark.parametrize("extra, message", [
    ([], "`pitch_um` is required with a reference scene (tubes-hex), e.g. --pitch-um"),
    (["--pitch-um", "14", "--wall-um", "8", "--r-outer-um", "7"], "`wall_um` must be in (0, r_outer_um = 7.0]"),
    (["--pitch-um", "14", "--wall-um", "2", "--jitter", "0.5"], "`jitter` must be in [0, 0.25]"),
    (["--pitch-um", "-1", "--wall-um", "2"], "`pitch_um` must be > 0 µm, got pitch_um=-1"),
])
def test_a_bad_reference_is_one_line_naming_the_field(capsys, extra, message):
    code, _, err = run(capsys, "trace", "--reference", "tubes-hex", "--thickness-mm", "0.02", "--delta-ri", "0.01",
                       *extra)
    assert code == 2 and len(err.strip().splitlines()) == 1 and message in err, err
    code, _, err = run(capsys, "trace", "--preset", "birch", "--thickness-mm", "0.02", "--delta-ri", "0.01",
                       "--wall-um", "2")
    assert code == 2 and "`--wall-um` applies to --reference, not --preset" in err


def test_output_read_by_a_pipe_that_closes_stops_in_one_line_with_sigpipes_status():
    """`twray trace --json | head`: the reader goes away before the summary is written; twray says so
    in one line and exits as a shell reports SIGPIPE (141), not with an error and its traceback."""
    proc = subprocess.Popen([sys.executable, "-m", "pipeline", "trace", "--preset", "birch", "--thickness-mm", "0.1",
                             "--rays", "20", "--delta-ri", "0.01", "--json"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    proc.stdout.close()  # the reader is gone before anything is written
    err = proc.stderr.read()
    assert proc.wait(timeout=120) == 141, err
    assert err.strip().splitlines()[-1] == "twray: stopped: the output's reader closed the pipe"


def test_an_interrupt_raised_inside_evaluated_source_still_exits_130_under_python_m(tmp_path):
    """CPython (3.11) marks a KeyboardInterrupt that ends code evaluated from a string as unhandled,
    even when it is caught later, and `python -m` then ends by SIGINT (-2) instead of with the
    code returned. A Ctrl-C that lands while a module is imported (dataclasses exec their methods'
    source) did so about once in 20 runs of `python -m pipeline generate`."""
    (tmp_path / "interrupted_in_exec.py").write_text(
        "import pipeline.cli as cli\n"
        "def parser():\n"
        "    exec('raise KeyboardInterrupt')\n"
        "cli.build_parser = parser\n"
        "raise SystemExit(cli.main([]))\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-m", "interrupted_in_exec"], capture_output=True, text=True, env=env,
                          timeout=120)
    assert proc.returncode == 130, (proc.returncode, proc.stderr)
    assert proc.stderr.strip().splitlines()[-1].startswith("twray: interrupted"), proc.stderr
