"""Publishing what twray writes: built aside, then renamed into place, so that a path holds at
every moment the old output or the new one, never half of one.

Wood volumes, per-ray datasets and study and camera Datasets all go through
:func:`publish`; Datasets carry a digest of their values, checked before a
rerun keeps them.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
from pathlib import Path

from .cache import dataset_digest, temp_name, warn, writing
from .params import ParameterError

PUBLISH_TRIES = 50


def staged_path(out: Path) -> Path:
    """A sibling path to build ``out`` in, so that a failure leaves nothing at ``out``
    (removed by a later run if this one is interrupted, see :func:`pipeline.cache.sweep_leftovers`)."""
    return temp_name(out, "partial")


def written_by_twray(path: Path) -> bool:
    """Whether ``path`` is a Zarr store twray wrote: a wood volume (attribute ``twray``) or a
    Dataset whose ``source`` attribute names twray."""
    path = Path(path)
    if path.is_symlink() or not (path / "zarr.json").is_file():
        return False
    try:
        attrs = json.loads((path / "zarr.json").read_text()).get("attributes", {})
    except (OSError, ValueError, AttributeError):
        return False
    return isinstance(attrs, dict) and ("twray" in attrs or str(attrs.get("source", "")).startswith("twray "))


def check_replaceable(out: Path, overwrite: bool) -> None:
    """Refuse an existing ``out`` unless ``overwrite`` is given and it is a store twray wrote.

    ``--overwrite`` replaces twray's own output, never another folder or file.
    """
    out = Path(out)
    if out.exists() or out.is_symlink():
        if not overwrite:
            raise ParameterError(f"`out` must not exist already (use --overwrite), got {str(out)!r}")
        # (a store another run is replacing this moment may be missing for an instant)
        if not any(written_by_twray(out) or not (out.exists() or out.is_symlink()) for _ in range(3)):
            raise ParameterError(f"`out` exists and is not a store twray wrote: --overwrite replaces only "
                                 f"those, got {str(out)!r}")


def publish(staged: Path, out: Path, overwrite: bool) -> None:
    """Move a finished store into place (a rename on one filesystem).

    An existing ``out`` (only a store twray wrote, with ``overwrite``) is first renamed
    aside, so that ``out`` holds at every moment either the old store or the new one.
    Runs publishing to one ``out`` at once each succeed; the last one's store stays.
    """
    check_replaceable(out, overwrite)
    taken = (errno.ENOTEMPTY, errno.EEXIST)  # ``out`` is there: another run's or the old store
    for _ in range(PUBLISH_TRIES):
        try:
            os.rename(staged, out)
            return
        except OSError as exc:
            if exc.errno not in taken:
                raise
        if not overwrite:
            check_replaceable(out, overwrite)  # another run wrote it meanwhile: refused
        old = temp_name(out, "old")
        try:
            os.rename(out, old)
        except FileNotFoundError:
            continue  # another run moved it aside first
        try:
            os.rename(staged, out)
        except OSError as exc:
            if exc.errno in taken:
                shutil.rmtree(old, ignore_errors=True)  # another run's store came in between:
                continue  # replace it in turn
            with contextlib.suppress(OSError):
                os.rename(old, out)
            raise
        shutil.rmtree(old, ignore_errors=True)
        return
    raise OSError(f"could not publish {out}: other runs kept replacing it")


DIGEST_ATTR = "twray_digest"


def is_current(out: Path, provenance: dict) -> bool:
    """Whether the Dataset at ``out`` carries exactly these provenance attributes and its
    values still match the digest recorded when it was written."""
    import xarray as xr

    try:
        with xr.open_zarr(out, consolidated=False) as ds:
            attrs = dict(ds.attrs)
            if not all(attrs.get(k) == v for k, v in provenance.items()):
                return False
            current = attrs.get(DIGEST_ATTR) == dataset_digest(ds.load())
    except Exception:  # noqa: BLE001 - anything unreadable is rebuilt
        return False
    if not current:
        warn("result %s is damaged (its values do not match their digest): writing it again", out)
    return current


def publish_dataset(build, out: Path, provenance: dict) -> Path:
    """Write the Dataset ``build()`` to ``out`` (built aside, then renamed into place).

    An existing Dataset whose attributes include ``provenance`` and whose values
    match their digest is kept.
    """
    if is_current(out, provenance):
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    staged = staged_path(out)
    ds = build()
    ds.attrs.update(provenance)
    ds.attrs[DIGEST_ATTR] = dataset_digest(ds)
    try:
        with writing(out, "dataset", staged):
            write_zarr(ds, staged)
        publish(staged, out, overwrite=True)
    finally:
        if staged.exists():
            shutil.rmtree(staged, ignore_errors=True)
    return out


def write_zarr(ds, path: Path) -> None:
    """``ds`` as a Zarr v3 store with consolidated metadata, so that a plain ``xr.open_zarr``
    opens it without a warning (zarr's own note that v3 has no consolidated metadata in its
    specification yet is silenced here)."""
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*[Cc]onsolidated metadata.*")
        ds.to_zarr(path, mode="w", zarr_format=3, consolidated=True)


def open_dataset(path: Path):
    """A result Dataset, loaded (the store is closed before plotting)."""
    import xarray as xr

    if not Path(path).exists():
        raise FileNotFoundError(f"{path} does not exist: run the make target that writes it (docs/guide.md)")
    with xr.open_zarr(path, consolidated=False) as ds:
        return ds.load()
