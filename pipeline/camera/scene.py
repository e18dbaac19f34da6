"""Camera YAML → validated image configurations (docs/methods.md#virtual-camera).

A camera file declares the sheet, the camera and the trace settings shared
by its images, and the images themselves::

    title: "Figure 5"
    sheet: {preset: birch, wood: {}, seed: 1, voxel_um: 0.5, thickness_mm: 0.5,
            width_mm: 1.5, length_mm: 1.0, ri_polymer: 1.53, delta_ri: 0.01, r_axis: x}
    camera: {sensor_px: [51, 51], pitch_um: 0.5, samples: 200, seed: 1}
    trace: {method: fast, fresnel: false}
    images:
      image-1:
        focal_mm: 6.25
        objective_mm: 162.5
        aperture_mm: 1.0
        gap_um: 2
        object: {kind: char, char: T, size_mm: 0.5}
      control:
        ...
        sheet: {delta_ri: 0}       # per-image changes of the sheet, or `sheet: none`

``--scale small`` keeps the geometry and divides the aperture samples and
the sheet thickness (see :data:`SCALES`).  Every unknown key or bad value
raises :class:`~pipeline.params.ParameterError` naming the file, the line
and the field.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

from ..optics.settings import INDEX_RANGE, TraceSettings, chosen_method, settings_for
from ..params import (ParameterError, WOOD_FIELDS, WoodParams, check_voxel, coerce_field, load_preset,
                      read_yaml_file, validate, yaml_locator)
from .lens import Camera, Sheet
from .targets import Target, make_target

SCALES = {
    "paper": {"samples": 1.0, "thickness": 1.0},
    "quick": {"samples": 0.1, "thickness": 1.0},  # the paper's sheet, a tenth of the aperture samples
    "small": {"samples": 0.1, "thickness": 0.2},
}

_TOP = {"title", "description", "sheet", "camera", "trace", "images"}
_SHEET = {"preset", "wood", "seed", "voxel_um", "thickness_mm", "width_mm", "length_mm",
          "ri_polymer", "delta_ri", "r_axis"}
_CAMERA = {"sensor_px", "pitch_um", "samples", "seed"}
_TRACE = {"method", "fresnel", "refine"}
_IMAGE = {"focal_mm", "objective_mm", "aperture_mm", "gap_um", "object", "sheet", "description"}
_SHEET_DEFAULTS = {"preset": "birch", "seed": 1, "voxel_um": 0.5, "thickness_mm": 0.5,
                   "width_mm": 1.5, "length_mm": 1.0, "ri_polymer": 1.53, "delta_ri": 0.01,
                   "r_axis": "x"}


@dataclass(frozen=True)
class ImageConfig:
    """One rendered image: camera, sheet (or None), object, trace settings."""

    name: str
    camera: Camera
    sheet: Sheet | None
    target: Target
    object_spec: dict
    settings: TraceSettings


@dataclass(frozen=True)
class CameraStudy:
    name: str
    path: Path
    text: str
    scale: str
    title: str
    images: tuple[ImageConfig, ...]


def load_camera(path, *, scale: str = "paper", method: str | None = None) -> CameraStudy:
    """Read and validate a camera file; expand it into images at ``scale``, traced with ``method``
    (``--method``) instead of the file's ``trace.method`` when given."""
    path = Path(path)
    if scale not in SCALES:
        raise ParameterError(f"`scale` must be one of {', '.join(SCALES)}, got scale={scale!r}")
    text, data = read_yaml_file(path, "camera file")
    where = yaml_locator(path, text)

    def fail(keys, msg):
        raise ParameterError(where(*keys) + msg)

    def mapping(value, keys, known):
        if value is None:
            return {}
        name = ".".join(keys)
        if not isinstance(value, dict):
            fail(keys, f"`{name}` must be a mapping, got {value!r}")
        for k in value:
            if k == "ri_wall" and "delta_ri" in known:
                fail(keys + (k,), f"`{name}.ri_wall` is given as `delta_ri`, the wall's index minus the "
                                  f"polymer's (ri_wall 1.54 with ri_polymer 1.53 is delta_ri: 0.01)")
            if k not in known:
                fail(keys + (k,), f"unknown key `{name}.{k}` (known: {', '.join(sorted(known))})")
        return value

    def number(value, keys, rule, ok):
        name = ".".join(keys)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            fail(keys, f"`{name}` must be a number, got {value!r}")
        if not ok(value):
            fail(keys, f"`{name}` must be {rule}, got {name}={value!r}")
        return float(value)

    def integer(value, keys, lo, hi):
        name = ".".join(keys)
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            fail(keys, f"`{name}` must be an integer in [{lo}, {hi}], got {value!r}")
        return value

    for k in data:
        if k not in _TOP:
            fail((k,), f"unknown key `{k}` (known: {', '.join(sorted(_TOP))})")
    if "images" not in data:
        raise ParameterError(f"{path}: `images` is required")
    f = SCALES[scale]
    base_sheet = dict(_SHEET_DEFAULTS)
    base_sheet.update(mapping(data.get("sheet"), ("sheet",), _SHEET))
    cam = mapping(data.get("camera"), ("camera",), _CAMERA)
    px = cam.get("sensor_px", [51, 51])
    if (not isinstance(px, list) or len(px) != 2
            or not all(isinstance(n, int) and not isinstance(n, bool) and 1 <= n <= 4096 for n in px)):
        fail(("camera", "sensor_px"), f"`camera.sensor_px` must be [rows, columns], each an integer "
                                      f"in [1, 4096], got {px!r}")
    pitch = number(cam.get("pitch_um", 0.5), ("camera", "pitch_um"), "> 0 µm", lambda v: v > 0)
    samples = integer(cam.get("samples", 200), ("camera", "samples"), 1, 100000)
    cam_seed = integer(cam.get("seed", 1), ("camera", "seed"), 0, 2**63 - 1)
    samples = max(1, int(round(samples * f["samples"])))

    trace = mapping(data.get("trace"), ("trace",), _TRACE)
    method = chosen_method(trace, method, fail)
    fresnel = trace.get("fresnel", False)
    if not isinstance(fresnel, bool):
        fail(("trace", "fresnel"), f"`trace.fresnel` must be true or false, got {fresnel!r}")
    refine = {"refine": integer(trace["refine"], ("trace", "refine"), 1, 8)} if "refine" in trace else {}
    settings = settings_for(method, exit="air", fresnel=fresnel, **refine)

    images = data["images"]
    if not isinstance(images, dict) or not images:
        fail(("images",), f"`images` must be a non-empty mapping of name: image, got {images!r}")
    out = []
    for name, spec in images.items():
        keys = ("images", str(name))
        if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", name):
            fail(keys, f"image names must be letters, digits, '-', '_' or '.', got {name!r}")
        spec = mapping(spec, keys, _IMAGE)
        for k in ("focal_mm", "objective_mm", "aperture_mm", "object"):
            if k not in spec:
                fail(keys, f"`images.{name}.{k}` is required")
        camera = Camera(
            focal_mm=number(spec["focal_mm"], keys + ("focal_mm",), "> 0 mm", lambda v: v > 0),
            objective_mm=number(spec["objective_mm"], keys + ("objective_mm",), "> 0 mm", lambda v: v > 0),
            aperture_mm=number(spec["aperture_mm"], keys + ("aperture_mm",), "> 0 mm", lambda v: v > 0),
            pixels=tuple(px), pitch_um=pitch, samples=samples, seed=cam_seed)
        try:
            camera.validate()
        except ParameterError as exc:
            fail(keys, f"`images.{name}`: {exc}")
        gap_um = number(spec.get("gap_um", 0.0), keys + ("gap_um",), ">= 0 µm", lambda v: v >= 0)
        if not isinstance(spec["object"], dict):
            fail(keys + ("object",), f"`images.{name}.object` must be a mapping, got {spec['object']!r}")
        try:
            target = make_target(spec["object"], base=path.parent)
        except ParameterError as exc:
            fail(keys + ("object",), f"`images.{name}.{str(exc).lstrip('`')}")
        sheet = None
        if spec.get("sheet") != "none":
            s = dict(base_sheet)
            own = mapping(spec.get("sheet"), keys + ("sheet",), _SHEET)
            s.update(own)
            sheet = _sheet(s, set(own), gap_um, f, fail, number, integer, keys)
            if (sheet.gap_um + sheet.thickness_um) * 1e-3 >= camera.objective_mm:
                fail(keys, f"`images.{name}`: the sheet must lie between the lens and the object: "
                           f"gap + thickness = {(sheet.gap_um + sheet.thickness_um) * 1e-3:g} mm must be "
                           f"< objective_mm = {camera.objective_mm:g}")
        out.append(ImageConfig(name, camera, sheet, target, dict(spec["object"]), settings))
    title = data.get("title", path.stem)
    if not isinstance(title, str):
        fail(("title",), f"`title` must be a string, got {title!r}")
    return CameraStudy(path.stem, path, text, scale, title, tuple(out))


def _sheet(s: dict, own, gap_um: float, f: dict, fail, number, integer, keys) -> Sheet:
    """The validated sheet of one image (``own``: the keys the image at ``keys`` overrides)."""

    def loc(k):
        return keys + ("sheet", k) if k in own else ("sheet", k)

    preset = s["preset"]
    if not isinstance(preset, str):
        fail(loc("preset"), f"`sheet.preset` must be a preset name, got {preset!r}")
    try:
        wood = load_preset(preset)
    except ParameterError as exc:
        fail(loc("preset"), str(exc))
    overrides = s.get("wood") or {}
    if not isinstance(overrides, dict):
        fail(loc("wood"), f"`sheet.wood` must be a mapping of microstructure parameters, "
                                f"got {overrides!r}")
    for k, v in overrides.items():
        if k not in WOOD_FIELDS:
            fail(loc("wood") + (k,), f"unknown microstructure parameter `sheet.wood.{k}` "
                                       f"(known: {', '.join(sorted(WOOD_FIELDS))})")
        try:
            wood[k] = coerce_field(k, v, "")
        except ParameterError as exc:
            fail(loc("wood") + (k,), f"`sheet.wood.{str(exc).lstrip('`')}")
    try:
        params: WoodParams = validate(WoodParams(**wood))
    except ParameterError as exc:
        fail(loc("wood"), str(exc))
    voxel = number(s["voxel_um"], loc("voxel_um"), "> 0 µm", lambda v: v > 0)
    try:
        check_voxel(voxel, params)
    except ParameterError as exc:
        fail(loc("voxel_um"), "`sheet." + str(exc).lstrip("`"))
    thickness_um = 1000.0 * number(s["thickness_mm"], loc("thickness_mm"), "> 0 mm",
                                   lambda v: v > 0) * f["thickness"]
    lo, hi = INDEX_RANGE
    index_rule, index_ok = f"in [{lo:g}, {hi:g}]", lambda v: lo <= v <= hi
    r_axis = s["r_axis"]
    if r_axis not in ("x", "y"):
        fail(loc("r_axis"), f"`sheet.r_axis` must be x or y (the sensor axis along R), got {r_axis!r}")
    sheet = Sheet(
        wood=params, seed=integer(s["seed"], loc("seed"), 0, 2**63 - 1), voxel_um=voxel,
        thickness_um=thickness_um,
        width_um=1000.0 * number(s["width_mm"], loc("width_mm"), "> 0 mm", lambda v: v > 0),
        length_um=1000.0 * number(s["length_mm"], loc("length_mm"), "> 0 mm", lambda v: v > 0),
        ri_polymer=number(s["ri_polymer"], loc("ri_polymer"), index_rule, index_ok),
        delta_ri=number(s["delta_ri"], loc("delta_ri"), "a number", lambda v: True),
        gap_um=gap_um, r_axis=r_axis)
    try:
        sheet.optics.validate()
    except ParameterError as exc:
        fail(loc("delta_ri"), str(exc))
    try:
        return sheet.validate()
    except ParameterError as exc:
        fail(keys if own else ("sheet",), str(exc))
