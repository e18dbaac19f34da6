"""Study YAML → validated scenes (one per value of the varied parameter).

A study file declares a base scene and one parameter to vary::

    title: "Table 1, study 2: refractive-index difference"
    preset: birch            # species preset (pipeline/presets/)
    wood: {}                 # overrides of the preset (WoodParams fields)
    seed: 1
    thickness_mm: 1.0
    delta_ri: 0.01
    ri_polymer: 1.49
    rays: 1000
    beam_um: 150
    voxel_um: 0.5
    realisations: 5          # woods per value: seeds seed, seed + 1, ...
    target_ci: {haze: 0.01, fwhm_r_rel: 0.03, over: woods}  # optional: trace more woods until met
    trace: {method: exact, exit: internal, fresnel: false}
    vary: {parameter: delta_ri, values: [-0.03, -0.02, -0.01, 0.01, 0.02, 0.03]}

``vary`` may instead map several parameters to their values, a product grid whose
Dataset has one dimension per parameter (in the file's order)::

    vary: {thickness_mm: [0.25, 0.5, 1, 2], delta_ri: [-0.01, -0.002, 0.002, 0.01]}

Instead of ``preset`` and ``wood``, ``reference: {name: tubes-square, pitch_um: 14.5,
wall_um: 2}`` traces a reference lattice of exact optics
(:mod:`pipeline.optics.references`); ``vary`` may then vary its ``pitch_um``, ``wall_um``,
``r_outer_um`` or ``jitter``.

The numbers are the paper's scale; ``--scale quick`` traces a twentieth of the
rays through the same samples and at most 5 of the woods, ``--scale small`` keeps the wood and
divides the rays, thickness and beam, and traces at most 2 realisations (see
:data:`SCALES`).  Every value is traced on the same realisations (realisation
r is the wood and beam of seed ``seed + r``), so differences between values
are paired: common random numbers.  Every unknown
key or bad value raises :class:`~pipeline.params.ParameterError` naming the
file, the line and the field.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..analysis import FwhmSpec, Target
from ..optics.references import REFERENCE_FIELDS, REFERENCES, Reference, reference
from ..optics.settings import (INDEX_RANGE, Optics, TraceSettings, check_paper_step, chosen_method, settings_for,
                               traced_voxel_um)
from ..params import (ParameterError, WOOD_FIELDS, WoodParams, check_voxel, coerce_field, load_preset,
                      read_yaml_file, validate, yaml_locator)

# What each scale does to the paper-scale numbers of a study file.
SCALES = {
    "paper": {"rays": 1.0, "thickness": 1.0, "beam": 1.0, "realisations": None},
    # The paper's samples and beam with a twentieth of the rays and at most 5 woods: every structure
    # is met as in the paper, the intervals are wider (the quick start).
    "quick": {"rays": 0.05, "thickness": 1.0, "beam": 1.0, "realisations": 5},
    # A tenth of the thickness and a quarter of the beam, which can miss the ray cells entirely (tests).
    "small": {"rays": 0.1, "thickness": 0.1, "beam": 0.25, "realisations": 2},
}
# Wood realisations per value when a study file does not say (at most the scale's cap).
REALISATIONS = 5

_TOP = {"title", "description", "preset", "wood", "reference", "seed", "thickness_mm", "delta_ri",
        "ri_polymer", "rays", "beam_um", "voxel_um", "trace", "vary", "target_ci", "realisations", "fwhm"}
_TRACE = {"method", "exit", "fresnel", "refine", "step_vox"}
_SCENE_VARIABLES = {
    # name: (dimension, units, long_name)
    "thickness_mm": ("thickness", "mm", "TW sample thickness along T"),
    "delta_ri": ("delta_ri", "1", "refractive-index difference, cell wall minus polymer"),
    "ri_polymer": ("ri_polymer", "1", "refractive index of the polymer"),
}


@dataclass(frozen=True)
class Scene:
    """One traced configuration: wood, sample, optics, beam and trace settings."""

    value: Any  # the varied parameter's value, as written in the study
    wood: WoodParams | None  # generated wood, or None for a reference lattice
    seed: int
    voxel_um: float
    thickness_um: float
    ri_polymer: float
    delta_ri: float
    rays: int
    beam_um: float
    settings: TraceSettings
    target: Target | None = None  # trace to this precision: `rays` is then the first batch
    realisation: int = 0  # which wood of the study's realisations (seed = study seed + realisation)
    reference: Reference | None = None  # a reference lattice instead of wood
    fwhm: FwhmSpec = FwhmSpec()  # which width FWHM_R and FWHM_L are (not part of the rays' keys)

    @property
    def pitch_um(self) -> float:
        """The cell pitch of what is traced [µm] (interfaces per µm scale as its inverse)."""
        return self.reference.pitch_um if self.reference is not None else self.wood.fibre_diameter_um

    @property
    def optics(self) -> Optics:
        """The optics this scene is traced with (the Fresnel streams keyed by its seed)."""
        return Optics.of_delta(self.ri_polymer, self.delta_ri, seed=self.seed)

    @property
    def traced_voxel_um(self) -> float:
        """The voxel the wood is generated and traced on [µm] (``settings.refine`` times smaller)."""
        return traced_voxel_um(self.voxel_um, self.settings)


@dataclass(frozen=True)
class Axis:
    """One varied parameter of a study: its dimension in the Dataset and its values."""

    parameter: str
    dimension: str
    units: str
    long_name: str
    values: tuple  # as the scenes hold them
    keys: tuple = ()  # where its values are in the study file

    def coordinate(self) -> list:
        """The values as a dimension coordinate (laminates as their ply notation)."""
        if self.parameter == "laminate":
            return ["none" if v is None else "/".join(f"{a:g}" for a in v) for v in self.values]
        return list(self.values)


@dataclass(frozen=True)
class Study:
    name: str
    path: Path
    text: str
    scale: str
    title: str
    parameter: str
    dimension: str
    units: str
    long_name: str
    scenes: tuple[Scene, ...]  # one per value (per cell of the grid, C order), each on realisation 0
    realisations: int = 1
    axes: tuple[Axis, ...] = ()  # the varied parameters (one for a 1-D study)
    unused: tuple[str, ...] = ()  # settings the file gives that its method does not use (voxel_um with exact)

    def realisation(self, index: int, r: int) -> Scene:
        """Value ``index`` on wood realisation ``r``: the wood and beam of seed ``seed + r``."""
        s = self.scenes[index]
        return dataclasses.replace(s, seed=s.seed + r, realisation=r)

    def all_scenes(self) -> list[Scene]:
        """Every traced scene: each value on each realisation."""
        return [self.realisation(i, r) for i in range(len(self.scenes)) for r in range(self.realisations)]

    @property
    def shape(self) -> tuple[int, ...]:
        """Values per varied parameter."""
        return tuple(len(a.values) for a in self.axes)

    def coordinate(self) -> list:
        """Each value's coordinate (1-D: the varied values, laminates as their ply notation; a grid:
        each cell's values joined, e.g. "0.5, 0.01")."""
        coords = [a.coordinate() for a in self.axes]
        if len(coords) == 1:
            return coords[0]
        return [", ".join(str(c[k]) for c, k in zip(coords, idx)) for idx in _cells(self.shape)]

    def label(self, index: int) -> str:
        """Value ``index`` as "dimension=value" (a grid: one per dimension)."""
        coords = [a.coordinate() for a in self.axes]
        idx = _cells(self.shape)[index]
        return ", ".join(f"{a.dimension}={c[k]}" for a, c, k in zip(self.axes, coords, idx))


def _cells(shape: tuple[int, ...]) -> list[tuple[int, ...]]:
    """Every index of a grid of ``shape``, in C order (the order of a study's scenes)."""
    return list(itertools.product(*(range(n) for n in shape)))


def load_study(path, *, scale: str = "paper", realisations: int | None = None, method: str | None = None,
               rays: int | None = None) -> Study:
    """Read and validate a study file; expand it into scenes at ``scale``.

    The command line's overrides: ``realisations`` (``--realisations``) replaces the
    file's ``realisations`` and the scale's cap, ``method`` (``--method``) its
    ``trace.method``, and ``rays`` (``--rays``) the rays traced per value and
    realisation (not scaled).
    """
    path = Path(path)
    if scale not in SCALES:
        raise ParameterError(f"`scale` must be one of {', '.join(SCALES)}, got scale={scale!r}")
    text, data = read_yaml_file(path, "study")
    where = yaml_locator(path, text)

    def fail(keys, msg):
        raise ParameterError(where(*keys) + msg)

    for k in data:
        if k not in _TOP:
            fail((k,), f"unknown key `{k}` (known: {', '.join(sorted(_TOP))})")
    for k in ("vary",):
        if k not in data:
            raise ParameterError(f"{path}: `{k}` is required")
    seed, n_real, n_file_rays = _counts(data, fail, scale, realisations, rays)
    number = _numbers(data, fail)
    base = {
        "thickness_mm": number("thickness_mm", 1.0, "> 0 mm", lambda v: v > 0),
        "delta_ri": number("delta_ri", 0.01, "in (-0.5, 0.5)", lambda v: abs(v) < 0.5),
        "ri_polymer": number("ri_polymer", 1.49, f"in [{INDEX_RANGE[0]:g}, {INDEX_RANGE[1]:g}]",
                             lambda v: INDEX_RANGE[0] <= v <= INDEX_RANGE[1]),
    }
    beam_um = number("beam_um", 150.0, "> 0 µm", lambda v: v > 0)
    voxel_um = number("voxel_um", 0.5, "> 0 µm", lambda v: v > 0)
    ref_base, wood, overrides = _wood_base(data, fail, where)
    settings = _trace_settings(data, method, fail, where)
    axes = [_axis(parameter, values, keys, ref_base, fail) for parameter, values, keys in _vary(data["vary"], fail)]
    f = SCALES[scale]
    n_rays = max(1, int(round(n_file_rays * f["rays"]))) if rays is None else rays
    common = dict(base=base, wood=wood, ref_base=ref_base, overrides=overrides, axes=axes, scale=scale,
                  voxel_um=voxel_um, settings=settings, where=where, fail=fail,
                  scene=dict(seed=int(seed), voxel_um=voxel_um, rays=n_rays, beam_um=beam_um * f["beam"],
                             settings=settings, fwhm=_fwhm(data.get("fwhm"), fail),
                             target=(_target(data.get("target_ci"), n_rays, f["rays"], n_real, f["realisations"], fail)
                                     if "target_ci" in data else None)))
    scenes = [_scene(combo, **common) for combo in itertools.product(*(a.values for a in axes))]
    first = axes[0]
    dimension = first.dimension if len(axes) == 1 else " × ".join(a.dimension for a in axes)
    title = data.get("title", path.stem)
    if not isinstance(title, str):
        fail(("title",), f"`title` must be a string, got {title!r}")
    return Study(name=path.stem, path=path, text=text, scale=scale, title=title,
                 parameter=" × ".join(a.parameter for a in axes), dimension=dimension, units=first.units,
                 long_name=first.long_name, scenes=tuple(scenes), realisations=n_real, axes=tuple(axes),
                 unused=("voxel_um",) if "voxel_um" in data and settings.medium_kind == "surfaces" else ())


def _numbers(data, fail):
    """A reader of the file's finite numbers: number(key, default, rule, ok) -> float."""
    def number(key, default, rule, ok):
        v = data.get(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            fail((key,), f"`{key}` must be a number, got {v!r}")
        if not ok(v):
            fail((key,), f"`{key}` must be {rule}, got {key}={v!r}")
        return float(v)
    return number


def _counts(data, fail, scale: str, realisations, rays) -> tuple[int, int, int]:
    """(seed, woods per value, the file's rays), each checked; the command line's ``realisations``
    replaces the file's and the scale's cap; its ``rays`` is checked here."""
    seed = data.get("seed", 1)
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**63:
        fail(("seed",), f"`seed` must be an integer in [0, 2**63), got {seed!r}")
    n_real = data.get("realisations", REALISATIONS)
    if isinstance(n_real, bool) or not isinstance(n_real, int) or not 1 <= n_real <= 1000:
        fail(("realisations",), f"`realisations` must be an integer in [1, 1000], got {n_real!r}")
    if SCALES[scale]["realisations"] is not None:
        n_real = min(n_real, SCALES[scale]["realisations"])
    if realisations is not None:
        if isinstance(realisations, bool) or not isinstance(realisations, int) or not 1 <= realisations <= 1000:
            raise ParameterError(f"`realisations` must be an integer in [1, 1000], got realisations={realisations!r}")
        n_real = realisations
    if seed + n_real > 2**63:
        fail(("seed",), f"`seed` + `realisations` must be below 2**63, got seed={seed}")
    if rays is not None and (isinstance(rays, bool) or not isinstance(rays, int) or rays < 1):
        raise ParameterError(f"`rays` must be a positive integer, got rays={rays!r}")
    n_rays = data.get("rays", 1000)
    if isinstance(n_rays, bool) or not isinstance(n_rays, int) or n_rays < 1:
        fail(("rays",), f"`rays` must be a positive integer, got {n_rays!r}")
    return seed, n_real, n_rays


def _wood_base(data, fail, where) -> tuple:
    """(reference fields, None, None) for a reference scene, or (None, the preset's fields with the
    file's ``wood`` overrides, those overrides)."""
    if "reference" in data:
        return _reference_fields(data, fail), None, None
    preset = data.get("preset", "birch")
    if not isinstance(preset, str):
        fail(("preset",), f"`preset` must be a preset name, got {preset!r}")
    try:
        wood = load_preset(preset)
    except ParameterError as exc:
        raise ParameterError(where("preset") + str(exc)) from None
    overrides = data.get("wood") or {}
    if not isinstance(overrides, dict):
        fail(("wood",), f"`wood` must be a mapping of microstructure parameters, got {overrides!r}")
    for k, v in overrides.items():
        if k not in WOOD_FIELDS:
            fail(("wood", k), f"unknown microstructure parameter `wood.{k}` "
                              f"(known: {', '.join(sorted(WOOD_FIELDS))})")
        wood[k] = coerce_field(k, v, "")
    return None, wood, overrides


def _trace_settings(data, method, fail, where) -> TraceSettings:
    """The file's ``trace`` block (its method replaced by ``method`` when given) as settings."""
    trace = data.get("trace") or {}
    if not isinstance(trace, dict):
        fail(("trace",), f"`trace` must be a mapping, got {trace!r}")
    for k in trace:
        if k not in _TRACE:
            fail(("trace", k), f"unknown key `trace.{k}` (known: {', '.join(sorted(_TRACE))})")
    method = chosen_method(trace, method, fail)
    if "fresnel" in trace and not isinstance(trace["fresnel"], bool):
        fail(("trace", "fresnel"), f"`trace.fresnel` must be true or false, got {trace['fresnel']!r}")
    changes = {}
    if "refine" in trace:
        changes["refine"] = trace["refine"]
    if "step_vox" in trace:
        step = trace["step_vox"]
        if isinstance(step, bool) or not isinstance(step, (int, float)) or not math.isfinite(step):
            fail(("trace", "step_vox"), f"`trace.step_vox` must be a number of voxels, got {step!r}")
        changes["step_vox"] = float(step)
    try:
        return settings_for(method, exit=trace.get("exit", "internal"),
                            fresnel=bool(trace.get("fresnel", False)), **changes)
    except ParameterError as exc:
        field = re.match(r"`(\w+)`", str(exc))
        key = ("trace", field.group(1)) if field and field.group(1) in trace else ("trace",)
        raise ParameterError(where(*key) + "`trace." + str(exc).lstrip("`")) from None


def _scene(combo, *, base, wood, ref_base, overrides, axes, scale, voxel_um, settings, where, fail, scene) -> Scene:
    """The scene of one combination of the varied values, every value checked."""
    f = SCALES[scale]
    scene_vars = dict(base)
    w = dict(wood or {})
    ref_fields = dict(ref_base or {})
    for ax, v in zip(axes, combo):
        if ax.parameter in _SCENE_VARIABLES:
            scene_vars[ax.parameter] = v
        elif ref_base is not None:
            ref_fields[ax.parameter] = v
        else:
            w[ax.parameter] = v
    v = combo[0] if len(axes) == 1 else combo
    vary_keys = axes[0].keys if len(axes) == 1 else ("vary",)
    thickness_um = scene_vars["thickness_mm"] * 1000.0 * f["thickness"]
    params = ref = None
    if ref_base is not None:
        try:
            ref = reference(**ref_fields)
        except ParameterError as exc:
            keys = vary_keys if any(a.parameter in REFERENCE_FIELDS for a in axes) else ("reference",)
            raise ParameterError(where(*keys) + f"value {v!r}: `reference.{str(exc).lstrip('`')}") from None
        wall = ref.wall_um
    else:
        if w.get("laminate") and "ply_thickness_um" not in overrides:
            # Equal plies through the thickness (docs/methods.md#laminates).
            w["ply_thickness_um"] = thickness_um / len(w["laminate"])
        try:
            params = validate(WoodParams(**w))
        except ParameterError as exc:
            raise ParameterError(where("wood") + f"value {v!r}: {exc}") from None
        try:
            check_voxel(voxel_um, params)
        except ParameterError as exc:
            fail(("voxel_um",), str(exc))
        wall = params.wall_thickness_um
    ri_polymer = scene_vars["ri_polymer"]
    try:
        Optics.of_delta(ri_polymer, scene_vars["delta_ri"]).validate()
    except ParameterError as exc:
        fail(("vary",), str(exc))
    try:
        check_paper_step(settings, voxel_um, wall)
    except ParameterError as exc:
        fail(("trace", "step_vox"), "`trace." + str(exc).lstrip("`"))
    if thickness_um < voxel_um:
        fail(("thickness_mm",), f"`thickness_mm` must be at least one voxel at scale {scale}, "
                                f"got {thickness_um:g} µm")
    return Scene(value=v, wood=params, thickness_um=thickness_um, ri_polymer=ri_polymer,
                 delta_ri=scene_vars["delta_ri"], reference=ref, **scene)


def _vary(vary, fail) -> list[tuple[str, Any, tuple]]:
    """``vary`` as (parameter, values, YAML keys of its values): {parameter, values} for one
    parameter, or a mapping of parameters to values for a product grid."""
    if isinstance(vary, dict) and set(vary) == {"parameter", "values"}:
        return [(vary["parameter"], vary["values"], ("vary", "values"))]
    if not isinstance(vary, dict) or not vary or "parameter" in vary or "values" in vary:
        fail(("vary",), "`vary` must be a mapping with `parameter` and `values`, or of parameters to their values "
                        f"(a grid, e.g. {{thickness_mm: [0.5, 1], delta_ri: [0.01, 0.02]}}), got {vary!r}")
    return [(k, v, ("vary", k)) for k, v in vary.items()]


def _axis(parameter, values, keys, ref_base, fail) -> Axis:
    """One varied parameter, its values checked and coerced as the scenes hold them."""
    legacy = keys[-1] == "values"
    name = "vary.values" if legacy else f"vary.{parameter}"
    known = (sorted(_SCENE_VARIABLES) + list(REFERENCE_FIELDS) if ref_base is not None
             else sorted(_SCENE_VARIABLES) + ["a microstructure parameter"])
    if parameter not in _SCENE_VARIABLES and parameter not in (REFERENCE_FIELDS if ref_base is not None
                                                               else WOOD_FIELDS):
        what = "of a reference scene " if ref_base is not None else ""
        if legacy:
            fail(("vary", "parameter"), f"`vary.parameter` {what}must be one of {', '.join(known)}, "
                                        f"got {parameter!r}")
        fail(("vary", parameter), f"unknown parameter `{name}`: a study {what}varies one of {', '.join(known)}")
    if not isinstance(values, list) or not values:
        fail(keys, f"`{name}` must be a non-empty list, got {values!r}")
    out, seen = [], set()
    for v in values:
        if parameter in _SCENE_VARIABLES or ref_base is not None:
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                fail(keys, f"`{name}` of {parameter} must be numbers, got {v!r}")
            v = float(v)
        else:
            if parameter == "laminate" and v in ("none", "None"):
                v = None
            try:
                v = coerce_field(parameter, v, "")
            except ParameterError as exc:
                fail(keys, f"`{name}`: {exc}")
        if repr(v) in seen:
            fail(keys, f"`{name}` must not repeat a value, got {v!r} twice")
        seen.add(repr(v))
        out.append(v)
    if parameter in _SCENE_VARIABLES:
        dimension, units, long_name = _SCENE_VARIABLES[parameter]
    else:
        dimension = parameter.removesuffix("_um")
        units = "um" if parameter.endswith("_um") else ("degree" if parameter == "laminate" else "1")
        long_name = parameter.replace("_", " ")
        if parameter == "laminate":
            long_name = "laminate ply angles in the L-R plane (none: solid wood)"
    return Axis(parameter, dimension, units, long_name, tuple(out), keys)


def _reference_fields(data: dict, fail) -> dict:
    """The ``reference`` mapping of a study file, checked (it replaces ``preset`` and ``wood``)."""
    for k in ("preset", "wood"):
        if k in data:
            fail((k,), f"`{k}` and `reference` exclude each other: a study traces wood or a reference lattice")
    value = data["reference"]
    if not isinstance(value, dict) or "name" not in value:
        fail(("reference",), f"`reference` must be a mapping with `name` ({', '.join(REFERENCES)}), "
                             f"`pitch_um` and `wall_um`, got {value!r}")
    for k, v in value.items():
        if k != "name" and k not in REFERENCE_FIELDS:
            fail(("reference", k), f"unknown key `reference.{k}` (known: name, {', '.join(REFERENCE_FIELDS)})")
        if k != "name" and (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)):
            fail(("reference", k), f"`reference.{k}` must be a number, got {v!r}")
    out = {k: value.get(k) for k in REFERENCE_FIELDS}
    out["jitter"] = out["jitter"] or 0.0
    try:
        reference(value["name"], **out)
    except ParameterError as exc:
        fail(("reference",), "`reference." + str(exc).lstrip("`"))
    return {"name": value["name"], **out}


def _fwhm(value, fail) -> FwhmSpec:
    """``fwhm``: {estimator, bin_deg, range_iqr} (docs/methods.md#fwhm-and-haze)."""
    if value is None:
        return FwhmSpec()
    if not isinstance(value, dict):
        fail(("fwhm",), f"`fwhm` must be a mapping such as {{estimator: half-max}}, got {value!r}")
    try:
        return FwhmSpec.from_dict(value)
    except (TypeError, ValueError) as exc:
        key = re.match(r"\W*`fwhm\.(\w+)`|unknown key `fwhm\.(\w+)`", str(exc))
        fail(("fwhm",) + ((next(g for g in key.groups() if g),) if key else ()), str(exc))


def _target(value, n_rays: int, factor: float, n_real: int, real_cap: int | None, fail) -> Target:
    """``target_ci``: a haze half-width, or {haze, fwhm_deg, fwhm_r_rel, over, max_rays,
    max_realisations} (max_rays scaled as rays; max_realisations at most the scale's cap)."""
    if not isinstance(value, dict):
        value = {"haze": value}
    known = ("fwhm_deg", "fwhm_r_rel", "haze", "max_rays", "max_realisations", "over")
    for k in value:
        if k not in known:
            fail(("target_ci", k), f"unknown key `target_ci.{k}` (known: {', '.join(known)})")
    out = {}
    for k, rule, ok in (("haze", "in (0, 0.5]", lambda v: 0 < v <= 0.5), ("fwhm_deg", "> 0 degree", lambda v: v > 0),
                        ("fwhm_r_rel", "in (0, 1]", lambda v: 0 < v <= 1)):
        if k in value and value[k] is not None:
            v = value[k]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not ok(v):
                fail(("target_ci",), f"`target_ci.{k}` must be a number {rule}, got {v!r}")
            out[k] = float(v)
    if not out:
        fail(("target_ci",), "`target_ci` must give `haze`, `fwhm_deg` or `fwhm_r_rel` (a 95 % CI half-width)")
    over = value.get("over", Target.over)
    if over not in ("rays", "woods"):
        fail(("target_ci", "over"), f"`target_ci.over` must be `rays` (more rays) or `woods` (more wood "
                                    f"realisations), got {over!r}")
    caps = {}
    for k, default in (("max_rays", Target.max_rays), ("max_realisations", Target.max_realisations)):
        cap = value.get(k, default)
        if isinstance(cap, bool) or not isinstance(cap, int) or cap < 1:
            fail(("target_ci",), f"`target_ci.{k}` must be a positive integer, got {cap!r}")
        caps[k] = cap
    max_rays = max(n_rays, int(round(caps["max_rays"] * factor)))
    max_real = max(n_real, min(caps["max_realisations"], real_cap) if real_cap is not None else caps["max_realisations"])
    return Target(haze=out.get("haze"), fwhm_deg=out.get("fwhm_deg"), fwhm_r_rel=out.get("fwhm_r_rel"), over=over,
                  max_rays=max_rays, max_realisations=max_real)


def with_realisations(study: Study, realisations: int) -> Study:
    """``study`` traced on ``realisations`` woods (the first ones are those it had)."""
    return dataclasses.replace(study, realisations=realisations)


def at_target_cap(study: Study) -> Study:
    """``study`` on as many woods as its target may trace (a target over woods: what an estimate
    must cover), else ``study`` itself."""
    target = study.scenes[0].target
    if target is None or target.over != "woods" or target.max_realisations <= study.realisations:
        return study
    return with_realisations(study, target.max_realisations)


def with_rays(study: Study, rays: int) -> Study:
    """``study`` with every scene traced with ``rays`` rays."""
    return dataclasses.replace(study, scenes=tuple(dataclasses.replace(s, rays=rays) for s in study.scenes))


def scene_record(scene: Scene) -> dict:
    """Canonical, JSON-ready description of a scene (for cache keys and provenance)."""
    out = dataclasses.asdict(scene)
    out["wood"] = None if scene.wood is None else scene.wood.to_dict()
    out["settings"] = scene.settings.to_dict()
    out["fwhm"] = scene.fwhm.to_dict()
    out["value"] = scene.value if not isinstance(scene.value, tuple) else list(scene.value)
    return out
