"""What a trace is asked to do: the tracing method and its settings, and the optics of the
sample (refractive indices, Fresnel, where angles are measured).

This is the one home of the rules about methods (which exist, what medium each
traces), the voxel a generated wood is traced on, and the refractive indices.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

from ..params import ParameterError

# Each method and the kind of medium it traces: "voxels" (a chunked two-phase volume,
# docs/methods.md#voxel-methods), "surfaces" (analytic walls, docs/methods.md#exact-references) or
# "fields" (a grey-level volume's iso-surface, docs/methods.md#iso-surfaces).
METHODS = {"paper": "voxels", "fast": "voxels", "accurate": "voxels", "exact": "surfaces", "iso": "fields"}
EXITS = ("internal", "air")
INDEX_RANGE = (1.0, 3.0)  # refractive indices of wall and polymer


def chosen_method(trace: dict, override, fail) -> str:
    """The method of a study or camera file: ``override`` (``--method``) if given, else its
    ``trace.method`` (default exact); a bad one is refused by name, or through ``fail(keys,
    message)`` (which raises with the file's line)."""
    if override is not None:
        return check_method(override, generated=True)
    try:
        return check_method(trace.get("method", "exact"), "trace.method", generated=True)
    except ParameterError as exc:
        fail(("trace", "method"), str(exc))
        raise


def check_method(method, field: str = "method", *, kind: str | None = None, generated: bool = False) -> str:
    """``method`` if it names a method (of medium ``kind``, when given; one that traces generated
    wood and lattices, with ``generated``); a ParameterError naming ``field`` otherwise."""
    known = [m for m, k in METHODS.items() if (kind is None or k == kind) and not (generated and k == "fields")]
    if method not in known:
        why = (" (iso traces a grey-level scan: twray trace --volume SCAN --method iso)"
               if generated and METHODS.get(method) == "fields" else "")
        raise ParameterError(f"`{field}` must be one of {', '.join(known)}, got {method!r}{why}")
    return method


@dataclass(frozen=True)
class VoxelSettings:
    """How the voxel methods find interfaces and normals.

    step_vox, svm_box : the paper's marching step and SVM sub-volume edge [voxels].
    sigma_vox, radius_vox : Gaussian σ of the smoothed-indicator normal and the
        truncation of its sum, about 3σ [voxels] (fast, accurate).
    newton, refit : Newton steps putting the crossing on the smoothed surface, and
        how many of them evaluate the window again (the others step on its
        second-order model).
    refine : generated wood (a function of position) is traced on voxels
        ``refine`` times smaller than the scene's (the same physical wood,
        refine³ as many voxels); a user volume is traced on its own voxels.
        Binary voxels alias walls nearly parallel to a grid axis into
        staircases whose smoothed normals err by degrees, the same at any
        voxel size in voxel units; against exact optics of many thin walls
        the error falls about as the voxel (docs/methods.md#accuracy).
    """

    step_vox: float = 2.0
    svm_box: int = 6
    sigma_vox: float = 2.0
    radius_vox: float = 6.0
    newton: int = 3
    refit: int = 1
    refine: int = 1

    def validate(self) -> "VoxelSettings":
        if not self.step_vox > 0:
            raise ParameterError(f"`step_vox` must be > 0 voxels, got {self.step_vox!r}")
        if not self.sigma_vox > 0 or not 1 <= self.radius_vox <= 24:
            raise ParameterError(f"`sigma_vox` must be > 0 and `radius_vox` in [1, 24], got "
                                 f"{self.sigma_vox!r}, {self.radius_vox!r}")
        if not 0 <= self.refit <= self.newton:
            raise ParameterError(f"`refit` must be in [0, newton = {self.newton!r}], got {self.refit!r}")
        if isinstance(self.refine, bool) or not isinstance(self.refine, int) or not 1 <= self.refine <= 8:
            raise ParameterError(f"`refine` must be an integer in [1, 8], got {self.refine!r}")
        return self


VOXEL_FIELDS = tuple(f.name for f in fields(VoxelSettings))


@dataclass(frozen=True)
class TraceSettings:
    """How rays are traced, whatever the medium.

    method : one of METHODS: "paper" (2-voxel steps, midpoint crossing, linear
        SVM on a 6×6×6 box), "fast" or "accurate" (exact voxel traversal,
        crossing on the voxel face, gradient of a Gaussian-smoothed wall
        indicator), "exact" (analytic surfaces).
    fresnel : partial Fresnel reflection at every interface.
    max_events : interfaces a ray may meet before it is "trapped" (a ray meets
        ~170 in 1.5 mm of birch; guided rays bounce on).
    exit : angles "internal" (in the sample) or after refraction into "air".
    voxel : the voxel methods' settings (None for a surface method).
    """

    method: str = "accurate"
    fresnel: bool = False
    max_events: int = 2000
    exit: str = "internal"
    voxel: VoxelSettings | None = None

    @property
    def medium_kind(self) -> str:
        """The kind of medium this method traces: "voxels" or "surfaces"."""
        return METHODS[self.method]

    @property
    def refine(self) -> int:
        """How many times smaller than the scene's voxel generated wood is traced on (1 for a
        surface method: it reads no voxels)."""
        return self.voxel.refine if self.voxel is not None else 1

    def validate(self) -> "TraceSettings":
        check_method(self.method)
        if self.exit not in EXITS:
            raise ParameterError(f"`exit` must be internal or air, got {self.exit!r}")
        if isinstance(self.max_events, bool) or not isinstance(self.max_events, int) or self.max_events < 1:
            raise ParameterError(f"`max_events` must be an integer >= 1, got {self.max_events!r}")
        if (self.voxel is None) != (self.medium_kind != "voxels"):
            raise ParameterError(f"`voxel` settings belong to the voxel methods, got method={self.method!r} "
                                 f"with voxel={self.voxel!r}")
        if self.voxel is not None:
            self.voxel.validate()
        return self

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TraceSettings":
        """Settings from ``to_dict``, or from the flat dict of one TraceSettings (what datasets
        written before the voxel settings had their own class hold)."""
        d = dict(d)
        voxel = d.pop("voxel", None)
        flat = {k: d.pop(k) for k in VOXEL_FIELDS if k in d}
        if METHODS.get(d.get("method")) == "voxels":
            voxel = VoxelSettings(**(voxel if voxel is not None else flat))
        return cls(**d, voxel=voxel)


PRESETS = {
    "paper": TraceSettings(method="paper", voxel=VoxelSettings()),
    # One window evaluation; the Newton steps run on its second-order model.
    "fast": TraceSettings(method="fast", voxel=VoxelSettings(sigma_vox=1.75, radius_vox=5.25, newton=3, refit=0)),
    # The window evaluated again after the first Newton step, on voxels half the scene's.
    "accurate": TraceSettings(method="accurate", voxel=VoxelSettings(sigma_vox=2.0, radius_vox=6.0, newton=3,
                                                                     refit=1, refine=2)),
    "exact": TraceSettings(method="exact"),
    "iso": TraceSettings(method="iso"),
}


def settings_for(method: str, **changes) -> TraceSettings:
    """The preset of ``method`` with ``changes``: fields of TraceSettings or of VoxelSettings
    (``step_vox=1.0``, ``refine=1``: a surface method has none)."""
    base = PRESETS[check_method(method)]
    voxel = {k: changes.pop(k) for k in VOXEL_FIELDS if k in changes}
    if voxel:
        if base.voxel is None:
            raise ParameterError(f"`{next(iter(voxel))}` applies to the voxel methods, not to method {method!r}")
        changes["voxel"] = replace(base.voxel, **voxel)
    return replace(base, **changes).validate()


def traced_voxel_um(voxel_um: float, settings: TraceSettings) -> float:
    """The voxel [µm] generated wood is traced on: the scene's, divided by the method's ``refine``."""
    return voxel_um / settings.refine


def check_paper_step(settings: TraceSettings, voxel_um: float, wall_um: float | None) -> None:
    """The paper's method steps ``step_vox`` voxels: a step as wide as the wall (``wall_um``; None:
    unknown) jumps over walls (docs/methods.md#voxel-methods: the paper's step is half a wall)."""
    if settings.method != "paper" or wall_um is None:
        return
    voxel = traced_voxel_um(voxel_um, settings)
    if settings.voxel.step_vox * voxel >= wall_um:
        raise ParameterError(f"`step_vox` must be smaller than the wall ({wall_um:g} µm = {wall_um / voxel:g} "
                             f"voxels), got step_vox={settings.voxel.step_vox:g}")


def wall_index(ri_polymer: float, delta_ri: float) -> float:
    """The cell wall's refractive index: the polymer's plus ΔRI (the one place it is derived)."""
    return ri_polymer + delta_ri


@dataclass(frozen=True)
class Optics:
    """The optics of a trace: the two phases' refractive indices and what the beam comes from.

    n_wall, n_poly : indices of the cell wall (phase 1) and the polymer filling
        the lumens (phase 0); :meth:`of_delta` builds them from ΔRI.
    n_outside : index of the medium the beam comes from (1.0: air); each ray is
        then refracted at the T = 0 face into the phase it enters (or reflected,
        status "reflected", where that is total).  None: the beam's directions
        are already inside the sample.
    seed : seed of the per-ray Fresnel streams.
    """

    n_wall: float
    n_poly: float
    n_outside: float | None = None
    seed: int = 0
    given_delta_ri: float | None = None  # ΔRI as given to of_delta (n_wall - n_poly may round it)

    @classmethod
    def of_delta(cls, ri_polymer: float, delta_ri: float, **kwargs) -> "Optics":
        """The optics of polymer index ``ri_polymer`` and wall index ``ri_polymer + delta_ri``."""
        return cls(n_wall=wall_index(ri_polymer, delta_ri), n_poly=ri_polymer, given_delta_ri=delta_ri, **kwargs)

    @property
    def delta_ri(self) -> float:
        """The wall's index minus the polymer's, as given where it was."""
        return self.given_delta_ri if self.given_delta_ri is not None else self.n_wall - self.n_poly

    def validate(self) -> "Optics":
        lo, hi = INDEX_RANGE
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in (self.n_wall, self.n_poly)):
            raise ParameterError(f"refractive indices must be finite numbers, got wall {self.n_wall!r} "
                                 f"and polymer {self.n_poly!r}")
        if not (lo <= self.n_poly <= hi and lo <= self.n_wall <= hi):
            raise ParameterError(f"`delta_ri` and `ri_polymer` must give indices in [{lo:g}, {hi:g}], got "
                                 f"polymer {self.n_poly:g} and wall {self.n_wall:g}")
        if self.n_outside is not None and not (math.isfinite(self.n_outside) and self.n_outside > 0):
            raise ParameterError(f"`n_outside` must be finite and > 0, got {self.n_outside!r}")
        return self
