"""twray's birch against the source study's own generator, by measurement.

The source's MATLAB generator has a public Python port (AI-TranspWood/
AITW_microstructures, ``wood_ms generate birch params.json``).  The port is
not a dependency of twray and is never imported: this script reads the NRRD
volumes it wrote (uint8 [R, T, L], 255 = wall with sigmoid edges, binarised
at 128), generates twray's birch at the same physical size for as many seeds,
measures both with :func:`pipeline.geometry_stats.volume_statistics`, and
writes ``results/geometry.json``: per source and statistic each seed's value,
the mean and a 95 % t-interval over seeds.  With ``--trace`` it also traces
every volume as a scan (``twray trace --volume``), same beam for both sources.

Example (volumes of 300 x 300 x 200 port voxels of 0.5 µm)::

    python benchmarks/port_geometry.py \\
        --port /work/port-runs/seed{1,2,3}/out/SaveBirch_0/FinalVolume3D/FinalVolume.nrrd \\
        --twray-seeds 1,2,3 --workdir /work/port-runs --trace
"""

from __future__ import annotations

import argparse
import gzip
import json
import math
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from scipy import stats

from pipeline.geometry_stats import is_ray_like, lumen_table, volume_statistics

ROOT = Path(__file__).resolve().parents[1]
TWRAY = str(Path(sys.executable).with_name("twray"))
TRACE_KEYS = ("haze", "fwhm_r_deg", "fwhm_l_deg", "interfaces_per_ray")


def read_nrrd(path: Path) -> np.ndarray:
    """A minimal NRRD reader: uint8, raw or gzip, attached data; returns C order (reversed sizes)."""
    blob = Path(path).read_bytes()
    head, _, data = blob.partition(b"\n\n")
    fields = {}
    for line in head.decode("ascii").splitlines()[1:]:
        if line.startswith("#") or ":" not in line:
            continue
        k, v = line.split(":", 1)
        fields[k.strip()] = v.strip().lstrip("=")
    if fields.get("type") not in ("uint8", "uchar", "unsigned char"):
        raise ValueError(f"{path}: only uint8 NRRD is supported, got {fields.get('type')}")
    if "data file" in fields:
        raise ValueError(f"{path}: detached data is not supported")
    enc = fields.get("encoding", "raw")
    if enc in ("gzip", "gz"):
        data = gzip.decompress(data)
    elif enc != "raw":
        raise ValueError(f"{path}: encoding {enc} is not supported")
    sizes = [int(s) for s in fields["sizes"].split()]
    # NRRD lists the fastest axis first; the port wrote its (x, y, z) array in C order.
    return np.frombuffer(data, np.uint8).reshape(sizes[::-1])


def t_interval(values: list[float]) -> dict:
    """Mean and 95 % Student-t interval over seeds."""
    x = np.asarray([v for v in values if v is not None and math.isfinite(v)], float)
    if x.size == 0:
        return {"mean": None, "ci95": [None, None], "n": 0}
    m = float(x.mean())
    if x.size < 2:
        return {"mean": m, "ci95": [None, None], "n": int(x.size)}
    h = float(stats.t.ppf(0.975, x.size - 1) * x.std(ddof=1) / math.sqrt(x.size))
    return {"mean": m, "ci95": [m - h, m + h], "n": int(x.size)}


def summarise(per_seed: list[dict]) -> dict:
    keys = [k for k, v in per_seed[0].items() if isinstance(v, (int, float)) and k != "voxel_um"]
    return {k: {"values": [s[k] for s in per_seed], **t_interval([s[k] for s in per_seed])} for k in keys}


def run(cmd: list[str], log: list[str], pythonpath: str | None = None) -> str:
    env = dict(os.environ, OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
        cmd = ["env", f"PYTHONPATH={pythonpath}", *cmd]
    log.append(shlex.join(cmd))
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    if res.returncode:
        raise RuntimeError(f"{shlex.join(cmd)} failed:\n{res.stderr[-2000:]}")
    return res.stdout


def twray_volume(seed: int, size_um, voxel_um: float, workdir: Path, log: list[str],
                 extra: tuple[str, ...] = ()) -> np.ndarray:
    from pipeline.microstructure.volume import WoodVolume
    tag = "-norays" if extra else ""
    out = workdir / f"twray{tag}-{seed}-{voxel_um:g}um.zarr"
    if not out.exists():
        run([TWRAY, "generate", "--preset", "birch", *extra, "--size-um", ",".join(f"{s:g}" for s in size_um),
             "--voxel-um", f"{voxel_um:g}", "--seed", str(seed), "--out", str(out), "--quiet"], log)
    return np.asarray(WoodVolume.open(out)[:, :, :])


def ray_detector_check(with_rays: np.ndarray, without: np.ndarray, voxel_um: float) -> dict:
    """The ray-slice detector against twray's truth: the slices where switching ray cells off
    changes voxels (ray tissue and its squeeze) are the slices that cross a ray group."""
    truth = (with_rays != without).any(axis=(0, 1))
    det = np.array([is_ray_like(lumen_table(with_rays[:, :, k], voxel_um)).any()
                    for k in range(with_rays.shape[2])])
    det_off = np.array([is_ray_like(lumen_table(without[:, :, k], voxel_um)).any()
                        for k in range(without.shape[2])])
    return {"truth_share": float(truth.mean()), "detected_share": float(det.mean()),
            "recall": float(det[truth].mean()) if truth.any() else None,
            "false_positive_share": float(det[~truth].mean()) if (~truth).any() else None,
            "detected_share_rays_off": float(det_off.mean())}


def trace(npy: Path, voxel_um: float, method: str, args, log: list[str]) -> dict:
    cmd = [TWRAY, "trace", "--volume", str(npy), "--voxel-um", f"{voxel_um:g}", "--delta-ri", "0.01",
           "--method", method, "--rays", str(args.rays), "--seed", "1", "--json", "--quiet"]
    if args.beam_um:
        cmd += ["--beam-um", f"{args.beam_um:g}"]
    t0 = time.perf_counter()
    res = json.loads(run(cmd, log, args.trace_pythonpath).strip().splitlines()[-1])
    res["wall_s"] = round(time.perf_counter() - t0, 1)
    return res


def finite(obj):
    """The document with NaN and infinities as null, so that the JSON is standard."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    return obj


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--port", nargs="+", type=Path, required=True, help="the port's FinalVolume.nrrd files")
    ap.add_argument("--port-voxel-um", type=float, default=0.5, help="voxel size the source assumes [µm]")
    ap.add_argument("--twray-seeds", default="1,2,3")
    ap.add_argument("--twray-voxel-um", type=float, default=0.5)
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/port-geometry"))
    ap.add_argument("--trace", action="store_true", help="also trace every volume (accurate and paper)")
    ap.add_argument("--rays", type=int, default=300)
    ap.add_argument("--beam-um", type=float, default=80.0, help="beam side [µm], centred on the R-L face")
    ap.add_argument("--trace-pythonpath", default=None,
                    help="PYTHONPATH for the trace commands (e.g. a checkout of a committed twray)")
    ap.add_argument("--extra", nargs="*", type=Path, default=[],
                    help="port volumes of another size: measured beside twray's birch of that size (one seed each)")
    ap.add_argument("--port-meta", type=Path, default=None,
                    help="JSON about how the port's volumes were made (commands, wall time, memory), copied in")
    ap.add_argument("--port-no-ray-cells", nargs="*", type=Path, default=[],
                    help="the port's volumes made with isExistRayCell 0: measured beside twray's birch without ray "
                         "cells, the same seeds (where FWHM_L without ray cells comes from)")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "geometry.json")
    args = ap.parse_args(argv)
    args.workdir.mkdir(parents=True, exist_ok=True)
    log: list[str] = [shlex.join([sys.executable, *sys.argv])]
    doc: dict = {}

    port_vols, port_runs = [], []
    for p in args.port:
        raw = read_nrrd(p)
        params = p.parent.parent / "params.json"
        port_runs.append({"nrrd": str(p), "shape": list(raw.shape),
                          "params": json.loads(params.read_text()) if params.exists() else None,
                          "grey_share_between_1_and_254": float(np.mean((raw > 0) & (raw < 255)))})
        port_vols.append((raw >= 128).astype(np.uint8))
    shape = port_vols[0].shape
    size_um = [n * args.port_voxel_um for n in shape]
    seeds = [int(s) for s in args.twray_seeds.split(",")]

    port_stats = [volume_statistics(v, args.port_voxel_um) for v in port_vols]
    twray_stats, ray_checks, twray_vols = [], [], []
    for s in seeds:
        v = twray_volume(s, size_um, args.twray_voxel_um, args.workdir, log)
        twray_stats.append(volume_statistics(v, args.twray_voxel_um))
        off = twray_volume(s, size_um, args.twray_voxel_um, args.workdir, log, ("--set", "ray_cells=false"))
        ray_checks.append({"seed": s, **ray_detector_check(v, off, args.twray_voxel_um)})
        twray_vols.append(v)

    doc.update({
        "description": "twray birch vs the source generator's Python port (AITW_microstructures), "
                       "measured with pipeline.geometry_stats.volume_statistics",
        "port": {"runs": port_runs, "voxel_um": args.port_voxel_um, "size_um": size_um,
                 "generation": json.loads(args.port_meta.read_text()) if args.port_meta else None,
                 "seeds": [r["params"].get("random_seed") if r["params"] else None for r in port_runs],
                 "per_seed": port_stats, "stats": summarise(port_stats)},
        "twray": {"preset": "birch", "voxel_um": args.twray_voxel_um, "size_um": size_um, "seeds": seeds,
                  "per_seed": twray_stats, "stats": summarise(twray_stats)},
        "ray_detector_validation": ray_checks,
        "commands": log,
    })
    checks = []
    for p in args.extra:
        raw = read_nrrd(p)
        params = p.parent.parent / "params.json"
        seed = json.loads(params.read_text()).get("random_seed", 1) if params.exists() else 1
        size = [n * args.port_voxel_um for n in raw.shape]
        v = twray_volume(seed, size, args.twray_voxel_um, args.workdir, log)
        checks.append({"nrrd": str(p), "size_um": size, "seed": seed,
                       "port": volume_statistics((raw >= 128).astype(np.uint8), args.port_voxel_um),
                       "twray": volume_statistics(v, args.twray_voxel_um)})
    if checks:
        doc["size_check"] = checks
    if args.port_no_ray_cells:
        p_stats, t_stats, p_seeds = [], [], []
        for p in args.port_no_ray_cells:
            params = p.parent.parent / "params.json"  # the port copies its parameters beside its output
            seed = json.loads(params.read_text()).get("random_seed", 1) if params.exists() else 1
            p_seeds.append(seed)
            p_stats.append(volume_statistics((read_nrrd(p) >= 128).astype(np.uint8), args.port_voxel_um))
            off = twray_volume(seed, size_um, args.twray_voxel_um, args.workdir, log, ("--set", "ray_cells=false"))
            t_stats.append(volume_statistics(off, args.twray_voxel_um))
        doc["no_ray_cells"] = {"seeds": p_seeds, "nrrd": [str(p) for p in args.port_no_ray_cells],
                               "port": {"per_seed": p_stats, "stats": summarise(p_stats)},
                               "twray": {"per_seed": t_stats, "stats": summarise(t_stats)}}
    if args.trace:
        tr = {"delta_ri": 0.01, "rays": args.rays, "beam_um": args.beam_um, "voxel_um": args.port_voxel_um,
              "thickness_um": size_um[1], "runs": []}
        pairs = [("port", doc["port"]["seeds"][i], v) for i, v in enumerate(port_vols)]
        if args.twray_voxel_um == args.port_voxel_um:
            pairs += [("twray", s, v) for s, v in zip(seeds, twray_vols)]
        for src, seed, v in pairs:
            npy = args.workdir / f"{src}-{seed}.npy"
            np.save(npy, v)
            for method in ("accurate", "paper"):
                res = trace(npy, args.port_voxel_um, method, args, log)
                tr["runs"].append({"source": src, "seed": seed, "method": method,
                                   **{k: res.get(k) for k in (*TRACE_KEYS, "wall_s")}, "raw": res})
        for src in ("port", "twray"):
            for method in ("accurate", "paper"):
                runs = [r for r in tr["runs"] if r["source"] == src and r["method"] == method]
                for k in TRACE_KEYS:
                    vals = [r[k] for r in runs if isinstance(r.get(k), (int, float))]
                    if vals:
                        tr.setdefault("stats", {}).setdefault(f"{src}/{method}", {})[k] = \
                            {"values": vals, **t_interval(vals)}
        doc["trace"] = tr
        doc["commands"] = log
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(finite(doc), indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
