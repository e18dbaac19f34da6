"""What every file twray writes says about how it was made, readable with xarray alone."""

from __future__ import annotations

import datetime
import json
import shlex
import sys

from . import __version__, versions


def provenance_attrs(inputs: dict, method: str | None = None) -> dict:
    """Attributes naming twray's and the generator's versions, the tracing method ``method``
    and its version (for what was traced), the full resolved ``inputs`` (as JSON), the date
    and the command line."""
    traced = {} if method is None else {"tracing_method": method, "tracer_version": versions.tracer(method)}
    return {
        "twray_version": __version__,
        **traced,
        "generator_version": versions.GENERATOR,
        "date_created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command_line": shlex.join([sys.argv[0].rsplit("/", 1)[-1], *sys.argv[1:]]),
        "inputs": json.dumps(inputs, sort_keys=True, default=str),
    }


def link_intervals(ds, level: float, n_boot: int) -> None:
    """Link each ``<name>_ci_lower/upper`` pair to ``<name>`` (CF ``ancillary_variables``) and
    record the interval's level and bootstrap size on both bounds."""
    for name in list(ds.data_vars):
        linked = []
        for kind in ("ci", "ray_ci"):  # ray_ci: the ray sampling alone (studies of several woods)
            lower, upper = f"{name}_{kind}_lower", f"{name}_{kind}_upper"
            if lower in ds and upper in ds:
                linked += [lower, upper]
                for bound in (lower, upper):
                    ds[bound].attrs.update({"confidence_level": level, "bootstrap_resamples": n_boot,
                                            "interval": "bootstrap percentile"})
        if linked:
            ds[name].attrs["ancillary_variables"] = " ".join(linked)
