"""Shared pieces of the command line: the parser, one-line errors, parsing of numbers and paths, help texts."""

from __future__ import annotations

import argparse
import math
import os
import re
from pathlib import Path

from ..params import ParameterError


EXIT_USAGE = 2


EXIT_ENVIRONMENT = 1  # the disk, memory or a worker failed; or a defect (its traceback in the log)


EXIT_INTERRUPTED = 130  # as a shell reports a process ended by Ctrl-C
EXIT_PIPE = 141  # as a shell reports a process whose output's reader went away (SIGPIPE)


class Parser(argparse.ArgumentParser):
    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        # Values such as `--delta-ri -1e-3` or `--incidence-deg -10,5` are values,
        # not options (argparse's own test knows only plain decimals); no option
        # of twray starts with a digit or a dot.
        self._negative_number_matcher = re.compile(r"^-[\d.]")

    def error(self, message):  # one line, not the usage block
        raise ParameterError(f"{self.prog}: {message}")


YES_HELP = ("run even if the estimate is above TWRAY_CONFIRM_CPU_HOURS (default 2 CPU-hours); what cannot "
            "fit memory or disk is refused anyway")


EXAMPLES = {
    "generate": ("Generate a wood microstructure (axes R, T, L; 1 = cell wall, 0 = polymer) from a species "
                 "preset and physical parameters into an OME-Zarr store, chunk by chunk on a Dask cluster, "
                 "or lazily (--lazy: chunks are made when first read). The same seed gives the same voxels "
                 "whatever the chunks or workers.",
                 ["twray generate --preset birch --size-um 150,150,100 --out birch.zarr",
                  "twray generate --preset balsa --set wall_thickness_um=1.2 --size-um 1500,1500,1500 --lazy "
                  "--out balsa.zarr",
                  "twray generate --config my-wood.yaml --size-um 300,300,300 --workers 2 --out w.zarr"]),
    "trace": ("Trace a square beam of rays through generated wood (--preset, made lazily as rays reach it) "
              "or a user volume (--volume) with Snell refraction and total internal reflection, and report "
              "FWHM_R and FWHM_L (by --fwhm: half-max, the default, lorentz-hist or lorentz-mle, with bootstrap "
              "95 % intervals) and haze.",
              ["twray trace --preset birch --thickness-mm 0.5 --delta-ri 0.01",
               "twray trace --volume sample.zarr --delta-ri -0.02 --rays 4000 --method fast --json",
               "twray trace --preset balsa --thickness-mm 1 --delta-ri 0.02 --exit air --out rays.nc"]),
    "study": ("Run parameter studies (the paper's Table 1) as a cached, incremental Dask graph: wood "
              "chunks, ray shards and summaries are cache entries, verified when read, and each study "
              "becomes results/<study>.zarr (an xarray Dataset). An unchanged rerun computes nothing.",
              ["twray study studies/table1/study-2.yaml --scale small",
               "twray study studies/table1/*.yaml --results results/paper --report results/paper/table1.md",
               "twray study my-study.yaml --scheduler-file scheduler.json --dry-run"]),
    "camera": ("Render what a thin-lens camera sees of an object through a TW sheet (the paper's Figure "
               "5): every pixel's aperture samples are traced through the sheet's wood, cached per image.",
               ["twray camera studies/camera/figure5.yaml --scale small",
                "twray camera studies/camera/figure5.yaml --workers 2 --results results/paper/camera"]),
    "figures": ("Draw the paper's figures from the result datasets: every Table 1 microstructure (sections "
                "and a 3D view), rays through 1.5 mm of birch, bar charts with intervals for every study, "
                "angle histograms with their Lorentz fits, and the camera images beside their ideal images.",
                ["twray figures", "twray figures --results results/small --out results/small/figures",
                 "twray figures --only studies,histograms"]),
    "report": ("Write the reproduction report (Markdown) from the result datasets: Table 1 with every "
               "interval, the trends as paired differences, the camera, the speed/accuracy trade and "
               "the commands that reproduce each item. Every number is read from a dataset.",
               ["twray report", "twray report --out /tmp/REPORT.md"]),
    "design": ("How well must the polymer match the wall? From a design map (a study over thickness × ΔRI, "
               "`make design`), the range of ΔRI that keeps haze at or below a limit at a given thickness, "
               "with its 95 % interval (wood-to-wood variation included), interpolated between the map's "
               "values; or, with --delta-ri, haze and FWHM_R at one ΔRI, inside the sample and in air.",
               ["twray design --preset birch --thickness-mm 1 --haze-max 0.2",
                "twray design --preset balsa --exit air --thickness-mm 0.5 --haze-max 0.1",
                "twray design --preset birch --thickness-mm 1 --delta-ri 0.005",
                "twray design --map results/quick/design/birch.zarr --thickness-mm 2 --haze-max 0.5"]),
    "cache": ("List, verify or clean the cache of studies and the camera.",
              ["twray cache ls", "twray cache verify --remove",
               "twray cache gc studies/table1/*.yaml --scale paper --dry-run"]),
    "slices": ("Write PNG cross-sections of a volume in the R-T, L-T and L-R planes (one pixel per voxel, "
               "wall black) and an overview figure with axes in µm.",
               ["twray slices birch.zarr --out slices/"]),
    "export-tiff": ("Write one 8-bit TIFF per L slice (rows R, columns T, ImageJ metadata in µm), for ImageJ, "
                    "Fiji or Avizo.",
                    ["twray export-tiff birch.zarr --out tiff/"]),
    "info": ("Print a volume's shape, voxel size, origin, parameters and how many chunks are generated, "
             "as JSON.",
             ["twray info birch.zarr"]),
    "resummarize": ("Recompute a study Dataset's FWHM, haze and intervals from its own rays (no ray traced): "
                    "every width estimator, intervals over woods, variance components.",
                    ["twray resummarize results/paper/study-1.zarr",
                     "twray resummarize results/paper/design/*.zarr --fwhm lorentz-hist"]),
    "wave": ("Where geometrical optics holds: trace each section of a regime file with `exact` rays and "
             "propagate scalar waves (white light, several beam positions and realisations) through the same "
             "section, then compare haze and FWHM_R cell by cell of ΔRI; cached case by case on a Dask cluster.",
             ["twray wave studies/wave/regime.yaml --results results/paper/wave",
              "twray wave studies/wave/regime.yaml --scale quick --results results/quick/wave"]),
}


def subparser(sub, name: str, help: str, **kwargs):
    """A subcommand whose --help has a description and examples."""
    import textwrap

    text, examples = EXAMPLES[name]
    epilog = "examples:\n" + "\n".join(f"  {e}" for e in examples)
    description = textwrap.fill(kwargs.pop("description", text), 88)
    return sub.add_parser(name, help=help, description=description, epilog=epilog,
                          formatter_class=argparse.RawDescriptionHelpFormatter, **kwargs)


def integer(text: str, name: str, minimum: int) -> int:
    try:
        value = int(text)
    except (TypeError, ValueError):
        raise ParameterError(f"`{name}` must be an integer, got {name}={text!r}") from None
    if value < minimum:
        raise ParameterError(f"`{name}` must be >= {minimum}, got {name}={value}")
    return value


def number(text: str, name: str) -> float:
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise ParameterError(f"`{name}` must be a number, got {name}={text!r}") from None
    if not math.isfinite(value):
        raise ParameterError(f"`{name}` must be a finite number, got {name}={text!r}")
    return value


def out_path(text: str, name: str = "out") -> Path:
    """An output path, absolute (the workers of a remote scheduler have their own working
    folder), whose folder exists or can be made and can be written (checked before any work)."""
    if not text or not text.strip():
        raise ParameterError(f"`{name}` must be a path, got {name}={text!r}")
    out = Path(text).absolute()
    parent = out.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise ParameterError(f"`{name}` must be under a folder, got {name}={text!r} ({parent} is a file)")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ParameterError(f"`{name}` must be in a folder you can write, got {name}={text!r} "
                             f"({parent} is read-only)")
    return out
