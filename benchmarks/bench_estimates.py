"""Every command's estimate against what it used (issue: estimates that hold).

Runs `generate`, `export-tiff`, `trace` (exact and the voxel methods), `study` and `camera`
in fresh folders, each as a child of benchmarks/usage.py (CPU of the whole process tree,
largest resident memory of any process in it), with TWRAY_ESTIMATES set so the command
records the estimate it checked before running; disk is what the command left under its
output and cache folders. Writes the "estimates" section of results/bench.json and
results/estimates.md.

    python benchmarks/bench_estimates.py --out results/bench.json [--only NAME ...] [--paper]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from _bench_json import write_section

ROOT = Path(__file__).resolve().parent.parent
TWRAY = [sys.executable, "-m", "pipeline"]
STUDY = ("preset: birch\nrealisations: 2\nrays: {rays}\nbeam_um: 100\nthickness_mm: {mm}\n"
         "vary: {{parameter: delta_ri, values: [0.01, -0.01]}}\n")
# Into air through 2 mm at |ΔRI| up to 0.03: a few rays are guided along R by total reflection at the
# walls to the event cap, laying strips of distortion tiles (which a worker keeps up to a ceiling).
AIR = ("preset: birch\nrealisations: 2\nrays: 500\nbeam_um: 150\nthickness_mm: 2\ntrace: {method: exact, exit: air}\n"
       "vary: {parameter: delta_ri, values: [-0.03, -0.01, 0.01, 0.03]}\n")

# name: (scale, command (strings with {tmp}), folders whose bytes are the disk it used)
CASES = {
    "generate-birch-64M": ("small", ["generate", "--preset", "birch", "--size-um", "100,100,100", "--voxel-um", "0.25",
                                     "--out", "{tmp}/v.zarr"], ["v.zarr"]),
    "generate-balsa-64M": ("small", ["generate", "--preset", "balsa", "--size-um", "200,200,200", "--voxel-um", "0.5",
                                     "--out", "{tmp}/v.zarr"], ["v.zarr"]),
    "generate-birch-1G": ("paper", ["generate", "--preset", "birch", "--size-um", "500,500,500", "--voxel-um", "0.5",
                                    "--out", "{tmp}/v.zarr"], ["v.zarr"]),
    "export-tiff-8M": ("small", ["generate", "--preset", "birch", "--size-um", "100,100,100", "--voxel-um", "0.5",
                                 "--out", "{tmp}/v.zarr", "--lazy", "--quiet", "&&", "export-tiff", "{tmp}/v.zarr",
                                 "--out", "{tmp}/tiff"], ["v.zarr", "tiff"]),
    "export-tiff-128M": ("paper", ["generate", "--preset", "birch", "--size-um", "200,200,400", "--voxel-um", "0.5",
                                   "--out", "{tmp}/v.zarr", "--lazy", "--quiet", "&&", "export-tiff", "{tmp}/v.zarr",
                                   "--out", "{tmp}/tiff"], ["v.zarr", "tiff"]),
    "trace-exact-0.5mm": ("small", ["trace", "--preset", "birch", "--thickness-mm", "0.5", "--rays", "100",
                                    "--beam-um", "100", "--method", "exact", "--delta-ri", "0.01", "--json"], []),
    "trace-exact-balsa-1mm": ("small", ["trace", "--preset", "balsa", "--thickness-mm", "1", "--rays", "100",
                                        "--beam-um", "150", "--method", "exact", "--delta-ri", "0.01", "--json"], []),
    "trace-exact-1.5mm": ("paper", ["trace", "--preset", "birch", "--thickness-mm", "1.5", "--rays", "1000",
                                    "--beam-um", "150", "--method", "exact", "--delta-ri", "0.01", "--json"], []),
    "trace-fast-0.25mm": ("small", ["trace", "--preset", "birch", "--thickness-mm", "0.25", "--rays", "200",
                                    "--beam-um", "100", "--method", "fast", "--delta-ri", "0.01", "--json"], []),
    "trace-accurate-0.5mm": ("paper", ["trace", "--preset", "birch", "--thickness-mm", "0.5", "--rays", "500",
                                       "--beam-um", "100", "--method", "accurate", "--delta-ri", "0.01", "--json"], []),
    "study-exact-small": ("small", ["study", "{tmp}/s.yaml", "--scale", "small", "--workers", "2",
                                    "--cache", "{tmp}/cache", "--results", "{tmp}/results"], ["cache", "results"]),
    "study-table1-2-quick": ("paper", ["study", str(ROOT / "studies/table1/study-2.yaml"), "--scale", "quick",
                                       "--workers", "2", "--cache", "{tmp}/cache", "--results", "{tmp}/results"],
                             ["cache", "results"]),
    "study-exact-air-2mm": ("paper", ["study", "{tmp}/air.yaml", "--workers", "2", "--cache", "{tmp}/cache",
                                      "--results", "{tmp}/results"], ["cache", "results"]),
    "camera-small": ("small", ["camera", str(ROOT / "studies/camera/figure5.yaml"), "--scale", "small", "--method", "fast",
                               "--workers", "2", "--cache", "{tmp}/cache", "--results", "{tmp}/results"],
                     ["cache", "results"]),
    "camera-quick": ("paper", ["camera", str(ROOT / "studies/camera/figure5.yaml"), "--scale", "quick", "--method", "fast",
                               "--cache", "{tmp}/cache", "--results", "{tmp}/results"], ["cache", "results"]),
}


def folder_bytes(path: Path) -> int:
    """Bytes of the files under ``path``, run logs excluded (they are not what a command makes)."""
    if path.is_file():
        return path.stat().st_size
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file() and f.parent.name != "logs")


def measure(argv: list[str], tmp: Path, folders: list[str]) -> dict:
    """Run one twray command line under usage.py: its estimate beside its CPU, peak memory and disk.
    ``&&`` joins several: those before the last set it up (run, not measured); the disk counts
    what all of them left."""
    record = tmp / "estimates.jsonl"
    env = {**os.environ, "TWRAY_ESTIMATES": str(record), "TWRAY_CONFIRM_CPU_HOURS": "1000"}
    cmds, cur = [], []
    for a in argv + ["&&"]:
        if a == "&&":
            cmds.append(cur)
            cur = []
        else:
            cur.append(a.format(tmp=tmp))
    used = {"cpu_s": 0.0, "peak_rss": 0, "wall_s": 0.0}
    est = {"cpu_s": 0.0, "memory": 0.0, "disk": 0.0}
    for cmd in cmds[:-1]:
        subprocess.run([*TWRAY, *cmd], capture_output=True, env=env, cwd=ROOT, check=True)
    for cmd in cmds[-1:]:
        start = len(record.read_text().splitlines()) if record.exists() else 0
        out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "usage.py"), "--", *TWRAY, *cmd,
                              *(["--quiet"] if cmd[0] != "export-tiff" else [])],
                             capture_output=True, text=True, env=env, cwd=ROOT, check=True)
        u = json.loads(out.stdout)
        if u["rc"] != 0:
            raise RuntimeError(f"{cmd}: exit {u['rc']}: {u['stderr']}")
        used["cpu_s"] += u["cpu_s"]
        used["wall_s"] += u["wall_s"]
        used["peak_rss"] = max(used["peak_rss"], u["peak_rss"])
        lines = record.read_text().splitlines()[start:]
        e = json.loads(lines[-1])
        est["cpu_s"] += e["cpu_s"]
        est["memory"] = max(est["memory"], e["memory"])
        est["disk"] += e["disk"]
    used["disk"] = sum(folder_bytes(tmp / f) for f in folders)
    return {"estimate": est, "used": used,
            "ratio": {"cpu": est["cpu_s"] / used["cpu_s"], "memory": est["memory"] / used["peak_rss"],
                      "disk": est["disk"] / used["disk"] if used["disk"] else None}}


def run_case(name: str) -> dict:
    _, argv, folders = CASES[name]
    with tempfile.TemporaryDirectory(prefix="twray-est-") as d:
        tmp = Path(d)
        (tmp / "s.yaml").write_text(STUDY.format(rays=150, mm=0.3))
        (tmp / "air.yaml").write_text(AIR)
        return measure(argv, tmp, folders)


def render(results: dict) -> str:
    from pipeline.limits import size

    lines = ["# Estimates against what the commands used", "",
             "Generated by `make bench-estimates` (benchmarks/bench_estimates.py): each command run in fresh "
             "folders on this machine; CPU is the whole process tree's (Dask workers included), memory the "
             "largest resident set of any of its processes, disk what it left under its outputs and cache. "
             "Ratio = estimate / used (the tests hold the small cases within 1.5x: memory and disk outright, CPU "
             "within 1.5x of their median ratio, which measures this host's speed against the one the constants "
             "were fitted on).", "",
             "| command | CPU est / used [s] | ratio | memory est / used | ratio | disk est / used | ratio |",
             "|---|---|---|---|---|---|---|"]
    for name, r in results.items():
        e, u, q = r["estimate"], r["used"], r["ratio"]
        disk = f"{q['disk']:.2f}" if q["disk"] is not None else "-"
        lines.append(f"| {name} | {e['cpu_s']:.1f} / {u['cpu_s']:.1f} | {q['cpu']:.2f} | {size(e['memory'])} / "
                     f"{size(u['peak_rss'])} | {q['memory']:.2f} | {size(e['disk'])} / {size(u['disk'])} | {disk} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/bench.json")
    ap.add_argument("--only", nargs="*", help="these cases only (the others kept from --out)")
    ap.add_argument("--paper", action="store_true", help="also the paper-scale cases (minutes)")
    args = ap.parse_args()
    names = args.only or [n for n, c in CASES.items() if args.paper or c[0] == "small"]
    old = json.loads(Path(args.out).read_text()).get("estimates", {}) if Path(args.out).exists() else {}
    results = dict(old)
    for name in names:
        results[name] = run_case(name)
        print(name, json.dumps(results[name]["ratio"]), file=sys.stderr)
    results = {n: results[n] for n in CASES if n in results}
    write_section(args.out, "estimates", results)
    (Path(args.out).parent / "estimates.md").write_text(render(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
