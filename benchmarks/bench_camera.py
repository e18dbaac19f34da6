"""The virtual camera: Figure 5 at full settings, cold and warm, and the blur anisotropy.

Writes the "camera" section of results/bench.json:
- figure5: ``twray camera studies/camera/figure5.yaml --method fast`` (51 × 51
  pixels, 200 aperture samples per pixel, 0.5 mm birch sheet on 0.5 µm voxels;
  ``make camera-fast``) in a fresh cache: first
  the three images of the paper's Figure 5 alone (``three_images_cold_s``,
  what the goal of 2 minutes is about), then the whole file, which adds the
  ΔRI = 0 control on the wood already generated (``control_s``), then again
  unchanged (``warm_s``); ``cold_s`` is the two cold runs together.  Also
  camera rays, peak RSS of the worker processes, wood chunks generated and
  the share of the sheet they cover;
- figure5_exact: the committed images, traced with ``exact`` (``make camera
  SCALE=paper YES=1``, about 1.5 h on 2 cores): not rerun here; an entry
  already in the file is kept;
- anisotropy: edge-spread widths (25-75 %, µm on the object) of a dark
  quadrant through the Figure 5 sheet with the image-1 and image-3 optics,
  the sheet's R along the sensor's x, against the ideal thin-lens image's.
"""

from __future__ import annotations

import argparse
import json
import re
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from _bench_json import write_section

ROOT = Path(__file__).resolve().parent.parent


def figure5(tmp: Path, scale: str) -> dict:
    import yaml

    full = ROOT / "studies" / "camera" / "figure5.yaml"
    data = yaml.safe_load(full.read_text())
    data["images"] = {k: v for k, v in data["images"].items() if not k.startswith("control")}
    three = tmp / "figure5.yaml"  # same images, same cache keys, without the control
    three.write_text(yaml.safe_dump(data, sort_keys=False, allow_unicode=True))
    out = {"scale": scale}
    report = []
    for run, path in (("three_images_cold", three), ("control", full), ("warm", full)):
        cmd = [sys.executable, "-m", "pipeline", "camera", str(path), "--scale", scale, "--method", "fast",
               "--cache", str(tmp / "cache"), "--results", str(tmp / "results" / run)]
        t0 = time.perf_counter()
        done = subprocess.run(cmd, check=True, capture_output=True, text=True)
        out[f"{run}_s"] = round(time.perf_counter() - t0, 1)
        if run == "control":
            report = [line.strip() for line in done.stdout.splitlines() if ": f " in line]
    out["cold_s"] = round(out["three_images_cold_s"] + out["control_s"], 1)
    out["report"] = report
    chunks = list((tmp / "cache" / "micro").rglob("c/*/*/*"))
    out["chunks_generated"] = len(chunks)
    # The sheet of the paper: 1.5 × 1 × 0.5 mm at 0.5 µm, in 64³ chunks.
    whole = -(-3000 // 64) * -(-2000 // 64) * -(-1000 // 64)
    if scale == "paper":
        out["chunks_of_whole_sheet"] = whole
        out["fraction_of_sheet"] = round(len(chunks) / whole, 3)
    n = re.findall(r"(\d+)/(\d+) samples lost", "\n".join(out["report"]))
    out["camera_rays"] = sum(int(b) for _, b in n)
    out["rays_per_s_cold"] = round(out["camera_rays"] / out["cold_s"])
    out["peak_rss_mb_workers"] = round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024)
    return out


def anisotropy(samples: int) -> dict:
    import numpy as np

    from pipeline.camera.lens import ideal_image, render_rows
    from pipeline.camera.dataset import edge_widths
    from pipeline.camera.scene import load_camera
    from pipeline.camera.targets import make_target
    from pipeline.optics.media import wood_medium

    study = load_camera(ROOT / "studies" / "camera" / "figure5.yaml", method="fast")
    out = {"samples": samples}
    for cfg in study.images[:3]:
        if cfg.name == "image-2":
            continue
        cam = replace(cfg.camera, samples=samples)
        sh = cfg.sheet
        t = make_target({"kind": "quadrant", "size_mm": 1.0})
        medium = wood_medium(sh.wood, seed=sh.seed, thickness_um=sh.thickness_um, voxel_um=sh.voxel_um,
                             settings=cfg.settings)
        t0 = time.perf_counter()
        img = render_rows(cam, sh, t, np.arange(cam.pixels[0]), settings=cfg.settings, medium=medium).image
        px = cam.pitch_um / cam.magnification
        out[cfg.name] = {"object_pixel_um": px, "ideal": edge_widths(ideal_image(cam, t), px),
                         "through_sheet": edge_widths(img, px), "r_axis": sh.r_axis,
                         "seconds": round(time.perf_counter() - t0, 1)}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/bench.json")
    ap.add_argument("--scale", default="paper", help="paper (full settings) or small")
    ap.add_argument("--samples", type=int, default=50, help="aperture samples of the anisotropy images")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        result = {"figure5": figure5(Path(tmp), args.scale), "anisotropy": anisotropy(args.samples)}
    before = json.loads(Path(args.out).read_text()).get("camera", {}) if Path(args.out).exists() else {}
    if "figure5_exact" in before:
        result["figure5_exact"] = before["figure5_exact"]
    write_section(args.out, "camera", result)


if __name__ == "__main__":
    main()
