"""What a wheel needs and what strict consumers read: package data, a clean import, strict JSON."""

import importlib.resources
import json
import subprocess
import sys

from pipeline.cli import main
from pipeline.trace_job import strict_json


def test_presets_are_package_data():
    presets = importlib.resources.files("pipeline") / "presets"
    assert {p.name for p in presets.iterdir() if p.name.endswith(".yaml")} >= {"birch.yaml", "balsa.yaml"}


def test_the_package_imports_without_a_warning():
    code = ("import pipeline.cli, pipeline.study.run, pipeline.camera.run, pipeline.inventory, "
            "pipeline.optics.validation")
    proc = subprocess.run([sys.executable, "-W", "error", "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


def test_json_output_is_strict_when_a_fit_is_undefined(capsys, tmp_path):
    assert strict_json({"a": float("nan"), "b": [1.0, float("inf")], "c": {"d": -float("inf")}}) == \
        '{"a": null, "b": [1.0, null], "c": {"d": null}}'
    # One ray: no bootstrap interval (NaN inside), null in the JSON.
    import numpy as np

    np.save(tmp_path / "v.npy", np.ones((20, 10, 20), np.uint8))
    code = main(["trace", "--volume", str(tmp_path / "v.npy"), "--delta-ri", "0.01", "--rays", "1",
                 "--beam-um", "1", "--json"])
    out = capsys.readouterr().out
    assert code == 0

    def refuse(constant):
        raise ValueError(f"not strict JSON: {constant}")

    summary = json.loads(out, parse_constant=refuse)
    assert summary["fwhm_r_ci_deg"] == [None, None] and summary["n_rays"] == 1


def test_every_subcommand_has_a_description_examples_and_help_for_every_flag():
    import argparse

    from pipeline.cli import build_parser

    parser = build_parser()
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert set(subs.choices) >= {"generate", "trace", "study", "camera", "cache", "slices", "export-tiff", "info"}
    for name, sub in subs.choices.items():
        text = sub.format_help()
        assert sub.description and "examples:\n  twray " + name in text, name
        for action in sub._actions:
            if not isinstance(action, argparse._HelpAction):
                assert action.help, f"twray {name} {action.option_strings or action.dest} has no help"


# What every written file says of how it was made; what was traced also names its method and its version.
PROVENANCE = ("twray_version", "generator_version", "date_created", "command_line", "inputs")
TRACED = PROVENANCE + ("tracing_method", "tracer_version")


def test_results_carry_their_provenance_and_open_with_plain_xarray_without_warnings(tmp_path, capsys):
    import warnings

    import xarray as xr

    study = tmp_path / "p.yaml"
    study.write_text("title: provenance\npreset: birch\nrays: 200\nbeam_um: 40\nthickness_mm: 0.2\n"
                     "delta_ri: 0.02\ntrace: {method: fast}\nvary: {parameter: delta_ri, values: [0.02]}\n")
    assert main(["study", str(study), "--scale", "small", "--cache", str(tmp_path / "c"), "--results",
                 str(tmp_path / "r"), "--workers", "1"]) == 0
    base = ["trace", "--preset", "birch", "--thickness-mm", "0.03", "--delta-ri", "0.01", "--rays", "20",
            "--seed", "7", "--method", "fast"]
    assert main(base + ["--out", str(tmp_path / "t.zarr")]) == 0
    assert main(base + ["--out", str(tmp_path / "t.nc")]) == 0
    capsys.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = xr.open_zarr(tmp_path / "r" / "p.zarr")
        tz = xr.open_zarr(tmp_path / "t.zarr")
    tn = xr.open_dataset(tmp_path / "t.nc")
    assert main(["generate", "--size-um", "10,10,10", "--seed", "5", "--out", str(tmp_path / "v.zarr")]) == 0
    import zarr

    volume = dict(zarr.open_group(tmp_path / "v.zarr", mode="r").attrs)
    assert all(k in volume for k in PROVENANCE) and json.loads(volume["inputs"])["seed"] == 5
    from pipeline.versions import tracer

    assert "tracer_version" not in volume  # a volume is generated, not traced
    for d in (ds, tz, tn):
        assert all(k in d.attrs for k in TRACED), sorted(d.attrs)
        assert d.attrs["tracing_method"] == "fast"
        assert d.attrs["tracer_version"] == tracer(d.attrs["tracing_method"]) and d.attrs["date_created"].startswith("20")
    inputs = json.loads(tz.attrs["inputs"])
    assert inputs["seed"] == 7 and inputs["rays"] == 20 and inputs["settings"]["method"] == "fast"
    assert inputs["params"]["species"] == "birch" and inputs["thickness_mm"] == 0.03
    scenes = json.loads(ds.attrs["inputs"])["scenes"]
    assert len(scenes) == 1 and scenes[0]["rays"] == 20
    assert ds.FWHM_R.attrs["ancillary_variables"] == ("FWHM_R_ci_lower FWHM_R_ci_upper "
                                                      "FWHM_R_ray_ci_lower FWHM_R_ray_ci_upper")
    assert ds.FWHM_R_ci_lower.attrs["confidence_level"] == 0.95
    assert ds.FWHM_R_ci_upper.attrs["bootstrap_resamples"] == 2000 and ds.haze.attrs["threshold_deg"] == 2.5


def test_progress_lines_appear_when_stdout_is_a_pipe_and_not_with_quiet(tmp_path):
    env = {**__import__("os").environ, "TWRAY_PROGRESS_EVERY_S": "0.5"}
    gen = [sys.executable, "-m", "pipeline", "generate", "--size-um", "100,100,100", "--chunks", "32,32,32"]
    proc = subprocess.run(gen + ["--out", str(tmp_path / "a.zarr")], capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    assert "twray generate: 343/343 tasks done" in proc.stderr, proc.stderr
    proc = subprocess.run(gen + ["--out", str(tmp_path / "b.zarr"), "--quiet"], capture_output=True, text=True,
                          env=env)
    assert proc.returncode == 0 and "tasks done" not in proc.stderr, proc.stderr
    study = tmp_path / "p.yaml"
    study.write_text("title: progress\npreset: birch\nrays: 200\nbeam_um: 40\nthickness_mm: 0.2\n"
                     "delta_ri: 0.02\ntrace: {method: fast}\nvary: {parameter: delta_ri, values: [0.01, 0.02]}\n")
    proc = subprocess.run([sys.executable, "-m", "pipeline", "study", str(study), "--scale", "small", "--cache",
                           str(tmp_path / "c"), "--results", str(tmp_path / "r"), "--workers", "1"],
                          capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("twray study: ") and "tasks done" in ln]
    assert lines and lines[-1].split()[2].split("/")[0] == lines[-1].split()[2].split("/")[1], proc.stderr


def test_a_long_trace_reports_progress_and_gives_the_numbers_of_one_call(tmp_path):
    env = {**__import__("os").environ, "TWRAY_PROGRESS_EVERY_S": "0.1"}
    argv = [sys.executable, "-m", "pipeline", "trace", "--preset", "birch", "--thickness-mm", "0.03",
            "--delta-ri", "0.02", "--rays", "1200", "--method", "fast", "--json"]
    batched = subprocess.run(argv, capture_output=True, text=True, env=env)
    quiet = subprocess.run(argv + ["--quiet"], capture_output=True, text=True, env=env)
    assert batched.returncode == 0 and quiet.returncode == 0, batched.stderr + quiet.stderr
    import re

    assert re.search(r"twray trace: (\d+)/\1 tasks done", batched.stderr), batched.stderr
    assert "tasks done" not in quiet.stderr
    a, b = json.loads(batched.stdout), json.loads(quiet.stdout)  # batches of 600 rays, or one call
    for key in ("fwhm_r_deg", "fwhm_l_deg", "haze", "fwhm_r_ci_deg", "interfaces_per_ray", "counts"):
        assert a[key] == b[key], key
