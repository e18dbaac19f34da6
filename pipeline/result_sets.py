"""The committed result datasets as the figures, the effects and the report read them: which
studies make Table 1, a study's varied dimension, how its values are printed, and the voxel a
scene record was traced on."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .publish import open_dataset

TABLE1 = ("study-1", "study-2", "study-3", "study-4", "study-5-1", "study-5-2", "study-6")


def load_table1(results: Path) -> dict:
    """{study name: Dataset} of the Table 1 studies under ``results``."""
    return {name: open_dataset(Path(results) / f"{name}.zarr") for name in TABLE1}


def study_dimension(ds) -> str:
    """The dimension a study varies (that of its FWHM_R)."""
    return ds["FWHM_R"].dims[0]


def value_label(v) -> str:
    """A study value as the report and the figures print it ("yes"/"no" for a switch)."""
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (float, np.floating, int, np.integer)):
        return f"{float(v):g}"
    return str(v)


def traced_voxel_um_of(record: dict) -> float:
    """The voxel a scene record's wood was traced on [µm] (its ``voxel_um`` over its method's refine)."""
    from .optics.settings import TraceSettings, traced_voxel_um

    return traced_voxel_um(record["voxel_um"], TraceSettings.from_dict(record["settings"]))
