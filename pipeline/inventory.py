"""What a cache folder holds: list its entries, verify them, remove what nothing uses.

The cache (``results/cache`` by default) has one folder per stage:
``micro/<key>.zarr`` (wood chunk stores), ``rays/<key>.npz``,
``summary/<key>.json``, ``pool/<key>.json``, ``camera/<key>.npz`` and, for an image not yet
whole, ``camera-rows/<key>.npz`` (its finished blocks of rows).  Every entry is named by
the key of what produced it and can say what that was (its record,
:func:`pipeline.cache.entry_record`; a wood store's attributes).
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from .cache import cache_key, check_json, check_npz, entry_record, is_leftover

STAGES = {"micro": ".zarr", "rays": ".npz", "summary": ".json", "pool": ".json", "camera": ".npz",
          "camera-rows": ".npz"}


@dataclass
class Entry:
    stage: str  # a key of STAGES, or "leftover" (an interrupted run's), or "unknown"
    path: Path
    size: int
    key: str = ""
    about: str = ""
    problems: list = field(default_factory=list)


def _size(path: Path) -> int:
    if path.is_dir() and not path.is_symlink():
        return sum(f.stat().st_size for f in path.rglob("*") if f.is_file() and not f.is_symlink())
    return path.lstat().st_size


def _wood_meta(path: Path) -> dict | None:
    try:
        return json.loads((path / "zarr.json").read_text())["attributes"]["twray"]
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _about(stage: str, path: Path) -> str:
    """One line of provenance."""
    if stage == "micro":
        meta = _wood_meta(path)
        if meta is None:
            return "not a wood store"
        n = sum(1 for _ in (path / "0" / "c").rglob("*") if _.is_file() and _.name.isdigit()) \
            if (path / "0" / "c").is_dir() else 0
        p = meta.get("params", {})
        return (f"{p.get('species', '?')} wood, seed {meta.get('seed')}, {meta.get('voxel_um')} um voxels, "
                f"{n} chunks, twray {meta.get('version')}")
    record = entry_record(path)
    if not isinstance(record, dict):
        return "no record"
    if stage == "rays":
        s = record.get("settings", {})
        lo, hi = record.get("range", ["?", "?"])
        return (f"rays {lo}-{hi} of wood {str(record.get('micro'))[:8]}, {s.get('method')}, "
                f"n_wall {record.get('n_wall')}, {record.get('thickness_vox')} voxels thick, "
                f"tracer {record.get('tracer')}")
    fw = record.get("fwhm", {}).get("estimator", "lorentz-mle")  # before summary 5 / pool 2 FWHM was the Lorentz 2γ
    if stage == "summary":
        return f"summary of {len(record.get('rays', []))} ray shards, FWHM {fw}"
    if stage == "pool":
        return (f"{len(record.get('summaries', []))} wood realisations pooled, FWHM {fw}, "
                f"{record.get('n_boot')} bootstrap draws")
    if stage == "camera":
        cam = record.get("camera", {})
        return f"image {cam.get('pixels')} px, {'with' if record.get('sheet') else 'without'} sheet, " \
               f"tracer {record.get('tracer')}"
    if stage == "camera-rows":
        image = record.get("image")
        lo, hi = record.get("rows", ["?", "?"])
        return f"rows {lo}-{hi} of camera image {cache_key(image)[:12] if isinstance(image, dict) else '?'}"
    return ""


def scan(cache) -> list[Entry]:
    """Every entry of ``cache`` (and what interrupted runs left there)."""
    cache = Path(cache)
    out = []
    for stage, suffix in STAGES.items():
        folder = cache / stage
        if not folder.is_dir():
            continue
        for p in sorted(folder.iterdir()):
            if is_leftover(p):
                out.append(Entry("leftover", p, _size(p)))
            elif p.name.endswith(suffix) and not p.name.startswith("."):
                out.append(Entry(stage, p, _size(p), p.name[: -len(suffix)], _about(stage, p)))
            elif not p.name.startswith("."):  # a live run's temporary files are skipped
                out.append(Entry("unknown", p, _size(p)))
        if stage == "micro":  # chunk files an interrupted run was writing
            for dirpath, dirs, files in os.walk(folder):
                for name in files:
                    p = Path(dirpath) / name
                    if p.parent != folder and is_leftover(p):
                        out.append(Entry("leftover", p, _size(p)))
    return out


def verify(entry: Entry) -> list[tuple[Path, str]]:
    """What is wrong with ``entry``: (the damaged file or folder, why) pairs, none if it is sound.
    A wood store's damaged chunks are named one by one (the rest of the store is sound)."""
    if entry.stage == "leftover":
        return [(entry.path, "left by an interrupted run")]
    if entry.stage == "micro":
        return _verify_wood(entry)
    if entry.stage in ("rays", "camera", "camera-rows"):
        why = check_npz(entry.path, entry.key)[1]
    elif entry.stage in ("summary", "pool"):
        why = check_json(entry.path, entry.key)[1]
    else:
        return []
    return [(entry.path, why)] if why else []


def _verify_wood(entry: Entry) -> list[tuple[Path, str]]:
    import zarr

    from .microstructure.store import WoodChunkStore, wood_record
    from .microstructure.volume import ARRAY, declares_digests
    from .params import WoodParams

    meta = _wood_meta(entry.path)
    if meta is None:
        return [(entry.path, "not a twray wood store")]
    try:
        chunks = tuple(zarr.open_array(entry.path / ARRAY, mode="r").chunks)
    except Exception as exc:  # noqa: BLE001 - any failure to open is the finding
        return [(entry.path, f"its array does not open: {type(exc).__name__}")]
    try:
        params = WoodParams.from_dict(meta.get("params") or {})
    except (TypeError, ValueError):
        return [(entry.path, "not the wood its key names (or made by an older twray)")]
    if cache_key(wood_record(params, meta.get("seed"), meta.get("voxel_um"), chunks)) != entry.key:
        return [(entry.path, "not the wood its key names (or made by an older twray)")]
    if not declares_digests(entry.path):
        return [(entry.path, "its chunks carry no digests")]
    store = WoodChunkStore(entry.path, params, seed=meta["seed"], voxel_um=meta["voxel_um"], chunks=chunks)
    problems = []
    root = entry.path / ARRAY / "c"
    for f in sorted(root.rglob("*")) if root.is_dir() else []:
        if f.is_file() and f.name.isdigit():
            d = tuple(int(x) for x in f.relative_to(root).parts)
            why = store.check(d)
            if why:
                problems.append((f, why))
    return problems


def remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)


def keys_in_use(files, scales, cache) -> set:
    """The keys of every entry the study and camera files need at ``scales``."""
    from .camera.plan import plan_blocks, plan_camera
    from .camera.scene import load_camera
    from .optics.settings import traced_voxel_um
    from .params import ParameterError
    from .microstructure.store import wood_record
    from .study.plan import plan_study
    from .study.spec import load_study

    keys = set()
    for f in files:
        for scale in scales:
            try:
                plan = plan_study(load_study(f, scale=scale), cache)
            except ParameterError as study_error:
                try:
                    entries = plan_camera(load_camera(f, scale=scale), cache)
                except ParameterError:
                    raise study_error from None
                for e in entries:
                    keys.add(e.key)
                    if not e.cached:  # the row blocks of an unfinished image
                        keys.update(b.key for b in plan_blocks(e, cache))
                    sh = e.config.sheet
                    if sh is not None and e.config.settings.medium_kind == "voxels":
                        keys.add(cache_key(wood_record(sh.wood, sh.seed,
                                                       traced_voxel_um(sh.voxel_um, e.config.settings))))
                continue
            keys.update(plan.micros)
            keys.update(s.key for s in plan.shards)
            keys.update(s.key for s in plan.summaries)
            keys.update(p.key for p in plan.pools)
    return keys


ACTIONS = ("ls", "verify", "gc")


@dataclass(frozen=True)
class CacheRequest:
    """What ``twray cache`` asks: ``action`` on the cache folder ``cache``; for gc, the study and
    camera files whose entries are kept (empty: every .yaml under ``studies/``) at ``scales``
    (None: every scale) and ``dry_run``; for verify, whether to ``remove`` damaged entries."""

    action: str
    cache: Path
    files: tuple = ()
    scales: tuple | None = None
    dry_run: bool = False
    remove: bool = False

    def validate(self) -> "CacheRequest":
        from .params import ParameterError

        if self.action not in ACTIONS:
            raise ParameterError(f"`action` must be one of {', '.join(ACTIONS)}, got {self.action!r}")
        if self.action != "gc" and (self.files or self.scales or self.dry_run):
            raise ParameterError(f"`{self.action}` takes no study files, --scale or --dry-run (those are gc's)")
        if self.action != "verify" and self.remove:
            raise ParameterError(f"`{self.action}` takes no --remove (that is verify's)")
        if not Path(self.cache).is_dir():
            raise ParameterError(f"`cache` must be an existing folder, got cache={str(self.cache)!r}")
        return self


@dataclass
class CacheOutcome:
    """What ``run`` found and did: every entry; the damaged files with why (verify); the entries
    removed or, with ``dry_run``, to remove (gc); what is not twray's and was left alone (gc)."""

    request: CacheRequest
    entries: list
    damaged: list = field(default_factory=list)
    dropped: list = field(default_factory=list)
    left_alone: list = field(default_factory=list)

    @property
    def exit_code(self) -> int:
        return 1 if self.damaged else 0


def run(request: CacheRequest) -> CacheOutcome:
    """List, verify or collect the cache of ``request`` (removing what it says to remove)."""
    from .params import ParameterError
    from .study.spec import SCALES

    request = request.validate()
    cache = Path(request.cache)
    out = CacheOutcome(request, scan(cache))
    if request.action == "verify":
        out.damaged = [found for e in out.entries for found in verify(e)]
        if request.remove:
            for path, _ in out.damaged:
                remove(path)
    elif request.action == "gc":
        files = list(request.files) or sorted(str(f) for f in Path("studies").rglob("*.yaml"))
        if not files:
            raise ParameterError("`files` must name the study and camera files whose entries to keep "
                                 "(no studies/ folder here)")
        keep = keys_in_use(files, list(request.scales or SCALES), cache)
        # Only twray's own entries are removed: anything else found there is named and left.
        out.left_alone = [e for e in out.entries if e.stage == "unknown"]
        out.dropped = [e for e in out.entries
                       if e.stage == "leftover" or (e.stage in STAGES and e.key not in keep)]
        if not request.dry_run:
            for e in out.dropped:
                remove(e.path)
    return out


def describe(outcome: CacheOutcome, *, as_json: bool = False) -> tuple[list[str], str]:
    """The lines for stdout (an entry, damaged file or removal each; with ``as_json``, ls's entries
    as JSON objects) and the one-line total for stderr."""
    from .limits import size

    req = outcome.request
    if req.action == "ls":
        lines = [json.dumps({"stage": e.stage, "key": e.key, "bytes": e.size, "path": str(e.path),
                             "about": e.about}) if as_json else
                 f"{e.stage:8s} {e.key or '-':24s} {size(e.size):>9s}  {e.about or e.path.name}"
                 for e in outcome.entries]
        return lines, f"{len(outcome.entries)} entries, {size(sum(e.size for e in outcome.entries))} in {req.cache}"
    if req.action == "verify":
        removed = " (removed)" if req.remove and outcome.damaged else ""
        return ([f"{path}: {why}" for path, why in outcome.damaged],
                f"{len(outcome.entries)} entries verified, {len(outcome.damaged)} damaged{removed}")
    verb = "would remove" if req.dry_run else "removed"
    lines = [f"left alone {e.path} (not a twray cache entry)" for e in outcome.left_alone]
    lines += [f"{verb} {e.path} ({size(e.size)})" for e in outcome.dropped]
    gone = size(sum(e.size for e in outcome.dropped))
    return lines, (f"{len(outcome.dropped)} entries ({gone}) {'to remove' if req.dry_run else 'removed'}, "
                   f"{len(outcome.entries) - len(outcome.dropped)} kept")
