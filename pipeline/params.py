"""Typed, validated descriptions of a wood microstructure.

Every user-facing quantity is physical (µm, degrees); voxels are an
implementation detail chosen by the resolution setting.  Invalid values
raise :class:`ParameterError`, whose message names the field, the value and
the rule, so the command line can print it as one line.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

# Species presets are package data (in the wheel too), read through importlib.resources.
PRESET_DIR = importlib.resources.files("pipeline") / "presets"


class ParameterError(ValueError):
    """A parameter has a bad name, type or value; the message says which and why."""


@dataclass(frozen=True)
class WoodParams:
    """Parameters of the hardwood microstructure model (docs/methods.md#parameter-reference).

    Lengths are in micrometres.  Cross-section lengths of the model scale
    with ``fibre_diameter_um``; lengths along the grain stay physical.
    """

    species: str = "birch"
    cell_shape: str = "ellipse"  # "ellipse" (hardwood fibres) or "polygon" (balsa)
    fibre_diameter_um: float = 14.5  # centre-to-centre spacing of fibres [µm]
    wall_thickness_um: float = 2.0  # wall between two neighbouring lumens [µm]
    wall_variation: float = 0.25  # per-cell inset spread, fraction of the nominal wall
    node_jitter: float = 0.1  # node jitter, fraction of the node pitch
    lumen_elongation_um: float = 1.0  # T contact nodes pushed outward [µm at 14.5 µm fibres]
    control_spacing_um: float = 50.0  # spacing of the jitter control slices along L [µm]
    fibre_length_um: float = 1170.5  # mean fibre length along L [µm]
    fibre_length_sd_um: float = 290.5
    end_plates: bool = True
    # Overlapping tapered fibre tips: consecutive fibres of a file meet along an oblique wall
    # that crosses the lumen over 2·fibre_tip_um along L, instead of a flat end plate.
    # 0: flat end plates (docs/methods.md#fibre-ends).
    fibre_tip_um: float = 0.0
    vessels: bool = True
    vessel_cluster_probability: float = 0.9  # proposal probability per vessel tile
    vessel_pair_fraction: float = 0.3
    vessel_triple_fraction: float = 0.15
    vessel_wall_um: float | None = None  # None: 5/3 (wall/2 + 0.5 µm·s), docs/methods.md#vessels
    ray_cells: bool = True
    ray_spacing_nodes: float = 20.0  # mean T spacing of ray columns [lattice nodes]
    ray_jitter_nodes: float = 5.0
    ray_seriate: int = 2  # ray cells side by side in T (birch: biseriate)
    ray_cell_width_um: float = 7.25  # lumen width along T [µm]
    ray_cell_height_um: float = 21.0  # cell pitch along L [µm]
    ray_cell_length_um: float = 31.0  # mean cell length along R [µm]
    ray_cell_length_sd_um: float = 7.5
    ray_group_cells: float = 11.33  # mean cells per group along L
    ray_group_cells_sd: float = 3.39
    ray_squeeze_um: float = 50.0  # support of the fibre squeeze beside a ray [µm at 14.5 µm]
    ray_ramp_um: float = 25.0  # taper of a ray group's ends along L [µm]
    distortion: float = 1.0  # amplitude factor of the local dipole distortions
    large_distortion_probability: float = 0.01  # per fibre centre
    global_bend_um: float = 6.0  # amplitude of the stationary bending of radial files [µm]
    global_bend_wavelength_um: float = 1500.0
    laminate: tuple[float, ...] | None = None  # ply angles in the L-R plane [degree]
    ply_thickness_um: float = 100.0  # thickness of each ply along T [µm]

    @property
    def node_pitch_um(self) -> float:
        return self.fibre_diameter_um / 2.0

    @property
    def scale(self) -> float:
        """Cross-section scale s = cell_r / 14.5 voxels (docs/methods.md#scaling-with-the-fibre-diameter)."""
        return self.node_pitch_um / 7.25

    def vessel_wall(self) -> float:
        if self.vessel_wall_um is not None:
            return self.vessel_wall_um
        return 5.0 / 3.0 * (self.wall_thickness_um / 2.0 + 0.5 * self.scale)

    def to_dict(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        if out["laminate"] is not None:
            out["laminate"] = list(out["laminate"])
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "WoodParams":
        """The inverse of :meth:`to_dict` (a stored wood's parameters), validated; a field the
        stored dict lacks (added later) takes its default."""
        d = dict(d)
        if d.get("laminate") is not None:
            d["laminate"] = tuple(d["laminate"])
        return validate(cls(**d))

    def key_dict(self) -> dict[str, Any]:
        """:meth:`to_dict` without the fields added later that sit at their neutral value.

        What cache keys hash: a wood that does not use a newer feature keeps the
        key (and the cached chunks) it had before the feature existed.
        """
        out = self.to_dict()
        for name, neutral in NEUTRAL_ADDED.items():
            if out[name] == neutral:
                del out[name]
        return out


# Fields added after cache keys were first written, with the value that reproduces the old wood.
NEUTRAL_ADDED = {"fibre_tip_um": 0.0}


WOOD_FIELDS = {f.name: f for f in dataclasses.fields(WoodParams)}
_BOOL = {"end_plates", "vessels", "ray_cells"}
_STR = {"species": None, "cell_shape": ("ellipse", "polygon")}
_INT = {"ray_seriate"}
_OPTIONAL = {"vessel_wall_um", "laminate"}


def coerce_field(name: str, value: Any, where: str) -> Any:
    """Convert one raw value (from YAML or ``--set``) to the field's type."""
    if name in _OPTIONAL and value is None:
        return None
    if name in _BOOL:
        if isinstance(value, bool):
            return value
        raise ParameterError(f"{where}`{name}` must be true or false, got {value!r}")
    if name in _STR:
        if not isinstance(value, str):
            raise ParameterError(f"{where}`{name}` must be a string, got {value!r}")
        allowed = _STR[name]
        if allowed and value not in allowed:
            raise ParameterError(f"{where}`{name}` must be one of {', '.join(allowed)}, got {value!r}")
        return value
    if name == "laminate":
        if isinstance(value, list) and len(value) == 1 and isinstance(value[0], str):
            value = value[0]  # YAML reads [0/-45/90] as a list of one string
        if isinstance(value, str):
            value = _parse_ply_string(value, where)
        if not isinstance(value, (list, tuple)) or not value:
            raise ParameterError(
                f"{where}`laminate` must be a non-empty list of ply angles in degrees "
                f"such as [0, -45, 90, 45, 0], got {value!r}"
            )
        return tuple(_number(name, v, where) for v in value)
    if name in _INT:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ParameterError(f"{where}`{name}` must be an integer, got {value!r}")
        return value
    return _number(name, value, where)


def _number(name: str, value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ParameterError(f"{where}`{name}` must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise ParameterError(f"{where}`{name}` must be finite, got {value!r}")
    return value


def _parse_ply_string(text: str, where: str) -> list[float]:
    """Parse the laminate notation ``[0/-45/90/45/0]``."""
    body = text.strip().strip("[]")
    try:
        return [float(p) for p in body.replace(",", "/").split("/") if p.strip()]
    except ValueError:
        raise ParameterError(
            f"{where}`laminate` must look like [0/-45/90/45/0], got {text!r}"
        ) from None


def _check(ok: bool, name: str, value: Any, rule: str) -> None:
    if not ok:
        raise ParameterError(f"`{name}` must be {rule}, got {name}={value!r}")


def validate(p: WoodParams) -> WoodParams:
    """Check the physical consistency of a parameter set; return it unchanged."""
    _check(p.fibre_diameter_um > 0, "fibre_diameter_um", p.fibre_diameter_um, "> 0 µm")
    _check(p.wall_thickness_um > 0, "wall_thickness_um", p.wall_thickness_um, "> 0 µm")
    # The lattice search tests the two rows and columns of centres around a point;
    # that is exact while a lumen (jitter with spline overshoot, elongation) stays
    # within 2 nodes of its centre, which these two bounds guarantee.
    _check(0 <= p.node_jitter <= 0.2, "node_jitter", p.node_jitter, "in [0, 0.2]")
    _check(0 <= p.lumen_elongation_um < 2.0, "lumen_elongation_um", p.lumen_elongation_um,
           "in [0, 2) µm (given at 14.5 µm fibres, scaled with the fibre diameter)")
    _check(0 <= p.wall_variation < 1, "wall_variation", p.wall_variation, "in [0, 1)")
    # The thickest inset wall (1 + wall_variation) with both contact nodes jittered
    # inward must leave a lumen; otherwise the "fibre" is solid and the geometry impossible.
    max_wall = 2.0 * (1.0 - 2.0 * p.node_jitter) / (1.0 + p.wall_variation) * p.node_pitch_um
    _check(
        p.wall_thickness_um < max_wall,
        "wall_thickness_um",
        p.wall_thickness_um,
        f"< {max_wall:.3g} µm so that every fibre keeps a lumen at fibre_diameter_um="
        f"{p.fibre_diameter_um:g}",
    )
    _check(p.control_spacing_um > 0, "control_spacing_um", p.control_spacing_um, "> 0 µm")
    _check(p.fibre_length_um > 0, "fibre_length_um", p.fibre_length_um, "> 0 µm")
    _check(p.fibre_length_sd_um >= 0, "fibre_length_sd_um", p.fibre_length_sd_um, ">= 0 µm")
    _check(0 <= p.fibre_tip_um <= p.fibre_length_um / 2, "fibre_tip_um", p.fibre_tip_um,
           f"in [0, fibre_length_um/2 = {p.fibre_length_um / 2:g}] µm so that a fibre's two tips fit in it")
    if p.fibre_tip_um > 0:
        _check(p.end_plates, "fibre_tip_um", p.fibre_tip_um, "0 when end_plates is false (tips are fibre ends)")
        _check(p.cell_shape == "ellipse", "fibre_tip_um", p.fibre_tip_um,
               f"0 for cell_shape {p.cell_shape} (tips are modelled for elliptical lumens)")
    for name in ("vessel_cluster_probability", "vessel_pair_fraction", "vessel_triple_fraction",
                 "large_distortion_probability"):
        v = getattr(p, name)
        _check(0 <= v <= 1, name, v, "a probability in [0, 1]")
    _check(p.vessel_pair_fraction + p.vessel_triple_fraction <= 1, "vessel_triple_fraction",
           p.vessel_triple_fraction, "<= 1 - vessel_pair_fraction")
    if p.vessel_wall_um is not None:
        _check(0 < p.vessel_wall_um < p.node_pitch_um, "vessel_wall_um", p.vessel_wall_um,
               "> 0 and below the fibre radius")
    _check(p.ray_spacing_nodes >= 8, "ray_spacing_nodes", p.ray_spacing_nodes, ">= 8 nodes")
    _check(0 <= p.ray_jitter_nodes < p.ray_spacing_nodes / 2 - 2, "ray_jitter_nodes",
           p.ray_jitter_nodes, "in [0, ray_spacing_nodes/2 - 2)")
    _check(1 <= p.ray_seriate <= 6, "ray_seriate", p.ray_seriate, "an integer in [1, 6]")
    for name in ("ray_cell_width_um", "ray_cell_height_um", "ray_cell_length_um",
                 "ray_squeeze_um", "ray_ramp_um", "ply_thickness_um", "global_bend_wavelength_um"):
        v = getattr(p, name)
        _check(v > 0, name, v, "> 0 µm")
    _check(p.ray_cell_height_um > p.wall_thickness_um, "ray_cell_height_um",
           p.ray_cell_height_um, f"> wall_thickness_um={p.wall_thickness_um:g}")
    _check(p.ray_cell_length_sd_um >= 0, "ray_cell_length_sd_um", p.ray_cell_length_sd_um, ">= 0 µm")
    _check(1 <= p.ray_group_cells <= 20, "ray_group_cells", p.ray_group_cells, "in [1, 20]")
    _check(p.ray_group_cells_sd >= 0, "ray_group_cells_sd", p.ray_group_cells_sd, ">= 0")
    _check(0 <= p.distortion <= 3, "distortion", p.distortion, "in [0, 3]")
    _check(p.global_bend_um >= 0, "global_bend_um", p.global_bend_um, ">= 0 µm")
    _check(p.global_bend_um * 2 * math.pi / p.global_bend_wavelength_um < 0.2, "global_bend_um",
           p.global_bend_um, "small enough that the bend slope 2π·A/λ stays below 0.2")
    if p.laminate is not None:
        _check(len(p.laminate) <= 64, "laminate", list(p.laminate), "at most 64 plies")
        for a in p.laminate:
            _check(-180 <= a <= 180, "laminate", list(p.laminate), "ply angles in [-180, 180] degrees")
    return p


def preset_names() -> list[str]:
    return sorted(p.name[: -len(".yaml")] for p in PRESET_DIR.iterdir() if p.name.endswith(".yaml"))


def read_yaml_file(path: Path, what: str) -> tuple[str, dict[str, Any]]:
    """The text of a YAML file and its top-level mapping; errors name the file and line."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ParameterError(f"cannot read {what} {str(path)!r}: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise ParameterError(f"{path}: must be a UTF-8 text file of YAML, got byte 0x{text_byte(exc)} at "
                             f"offset {exc.start}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" line {mark.line + 1}" if mark else ""
        raise ParameterError(f"{path}{line}: not valid YAML ({getattr(exc, 'problem', exc)})") from None
    if data is None:
        return text, {}
    if not isinstance(data, dict):
        raise ParameterError(f"{path}: must be a mapping of key: value, got {type(data).__name__}")
    return text, data


def text_byte(exc: UnicodeDecodeError) -> str:
    return exc.object[exc.start:exc.start + 1].hex()


def _read_yaml(path: Path, what: str) -> dict[str, Any]:
    return read_yaml_file(path, what)[1]


def key_lines(text: str) -> dict[tuple, int]:
    """Line numbers of the keys of a YAML document at every depth, as key paths."""
    out: dict[tuple, int] = {}

    def walk(node, prefix):
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                out[prefix + (str(k.value),)] = k.start_mark.line + 1
                walk(v, prefix + (str(k.value),))

    walk(yaml.compose(text), ())
    return out


def yaml_locator(path: Path, text: str):
    """``where(*keys)`` → "FILE line N: " for the deepest prefix of the key path found in ``text``."""
    lines = key_lines(text)

    def where(*keys) -> str:
        while keys and keys not in lines:
            keys = keys[:-1]
        return f"{path} line {lines.get(keys, '?')}: "

    return where


def _key_lines(path: Path) -> dict[str, int]:
    """Line numbers of the top-level keys of a YAML file, for error messages."""
    return {k[0]: v for k, v in key_lines(path.read_text()).items() if len(k) == 1}


def _apply(base: dict[str, Any], updates: dict[str, Any], where_of) -> None:
    for key, value in updates.items():
        if key not in WOOD_FIELDS:
            near = ", ".join(sorted(WOOD_FIELDS))
            raise ParameterError(f"{where_of(key)}unknown parameter `{key}` (known: {near})")
        base[key] = coerce_field(key, value, where_of(key))


def load_preset(name: str) -> dict[str, Any]:
    path = PRESET_DIR / f"{name}.yaml"
    if not path.is_file():
        raise ParameterError(
            f"`preset` must be one of {', '.join(preset_names())}, got preset={name!r}"
        )
    data = _read_yaml(path, "preset")
    values: dict[str, Any] = {}
    lines = _key_lines(path)
    _apply(values, data, lambda k: f"{path.name} line {lines.get(k, '?')}: ")
    return values


def parse_set(items: list[str]) -> dict[str, Any]:
    """Parse ``--set key=value`` items; values are read as YAML scalars."""
    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise ParameterError(f"`--set` takes key=value, got {item!r}")
        key, raw = item.split("=", 1)
        key = key.strip()
        try:
            value = yaml.safe_load(raw) if raw.strip() else None
        except yaml.YAMLError:
            value = raw
        out[key] = value
    return out


def build_params(
    preset: str | None = "birch",
    config: str | Path | None = None,
    overrides: dict[str, Any] | None = None,
) -> WoodParams:
    """Combine a species preset, a YAML config and overrides (in that order).

    A config file may name its own ``preset``; an explicit ``preset`` argument
    other than the default wins over it.
    """
    values: dict[str, Any] = {}
    cfg: dict[str, Any] = {}
    cfg_path = Path(config) if config is not None else None
    if cfg_path is not None:
        cfg = dict(_read_yaml(cfg_path, "config"))
        if "preset" in cfg:
            cfg_preset = cfg.pop("preset")
            if not isinstance(cfg_preset, str):
                raise ParameterError(f"{cfg_path}: `preset` must be a preset name, got {cfg_preset!r}")
            if preset in (None, "birch"):
                preset = cfg_preset
    if preset is not None:
        values.update(load_preset(preset))
    if cfg_path is not None:
        lines = _key_lines(cfg_path)
        _apply(values, cfg, lambda k: f"{cfg_path} line {lines.get(k, '?')}: ")
    if overrides:
        _apply(values, overrides, lambda k: "--set ")
    return validate(WoodParams(**values))


def parse_triple(text: str, name: str, *, positive: bool, integer: bool = False) -> tuple:
    """Parse ``R,T,L`` from the command line."""
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) != 3:
        raise ParameterError(f"`{name}` must be three comma-separated numbers R,T,L, got {text!r}")
    try:
        vals = [int(p) if integer else float(p) for p in parts]
    except ValueError:
        kind = "integers" if integer else "numbers"
        raise ParameterError(f"`{name}` must be three {kind} R,T,L, got {text!r}") from None
    for v in vals:
        if not math.isfinite(v):
            raise ParameterError(f"`{name}` must be finite, got {text!r}")
        if positive and v <= 0:
            raise ParameterError(f"`{name}` must be > 0 along every axis, got {text!r}")
    return tuple(vals)


@dataclass(frozen=True)
class Grid:
    """The voxel grid of a volume: where voxel (0, 0, 0) is and how big voxels are.

    Voxel (i, j, k) has its centre at ``origin_um + (index + 0.5) * voxel_um``
    along [R, T, L].
    """

    shape: tuple[int, int, int]
    voxel_um: float = 0.5
    origin_um: tuple[float, float, float] = (0.0, 0.0, 0.0)


MIN_VOXEL_UM = 0.01  # 10 nm: finer resolves nothing of the model (its phase is sampled at 0.04 µm by the waves)


def check_voxel(voxel_um, params: WoodParams) -> float:
    """``voxel_um`` if it samples the wood of ``params``: at least MIN_VOXEL_UM and at most half the
    wall (at least two voxels across a wall); a ParameterError naming the rule otherwise."""
    if not (isinstance(voxel_um, (int, float)) and math.isfinite(voxel_um) and voxel_um >= MIN_VOXEL_UM):
        raise ParameterError(f"`voxel_um` must be >= {MIN_VOXEL_UM:g} µm, got voxel_um={voxel_um!r}")
    thinnest = params.wall_thickness_um
    if voxel_um > thinnest / 2:
        raise ParameterError(
            f"`voxel_um` must be <= wall_thickness_um/2 = {thinnest / 2:g} µm "
            f"(at least two voxels across a wall), got voxel_um={voxel_um:g}"
        )
    return voxel_um


def make_grid(size_um, voxel_um: float, origin_um, params: WoodParams) -> Grid:
    """Validate the sampling of a sample of ``size_um`` and return its grid."""
    check_voxel(voxel_um, params)
    shape = []
    for axis, s in zip("RTL", size_um):
        n = int(round(s / voxel_um))
        if n < 1:
            raise ParameterError(
                f"`size_um` must be at least one voxel ({voxel_um:g} µm) along {axis}, got {s:g}"
            )
        shape.append(n)
    if math.prod(shape) > 10**13:
        raise ParameterError(f"`size_um` must describe at most 1e13 voxels, got {math.prod(shape):.3g}")
    return Grid(tuple(shape), float(voxel_um), tuple(float(o) for o in origin_um))
