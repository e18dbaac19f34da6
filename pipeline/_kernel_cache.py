"""Where Numba keeps the compiled kernels: a directory keyed by a hash of the kernels' sources.

Numba's on-disk cache checks only the timestamp of a function's own file, so a kernel changed in
one file would leave stale compiled callers in other files (more so as small kernels are inlined
into their callers).  Keying the whole cache by the sources of every file that defines a kernel
makes any such change compile afresh, and never reuses code compiled from other sources.  Runs
when :mod:`pipeline` is imported, before Numba is; a ``NUMBA_CACHE_DIR`` set by the user wins.
"""

import hashlib
import os
import shutil
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent
KERNEL_MARKERS = (b"njit", b"@intrinsic", b"@overload")
KEEP = 3  # cache directories kept for other versions of the sources (most recently used first)


def sources_key(package: Path = PACKAGE) -> str:
    """Hash of the path and bytes of every module of ``package`` that defines a Numba kernel."""
    h = hashlib.sha256()
    for path in sorted(package.rglob("*.py")):
        data = path.read_bytes()
        if any(m in data for m in KERNEL_MARKERS):
            h.update(path.relative_to(package).as_posix().encode() + b"\0" + data + b"\0")
    return h.hexdigest()[:16]


def cache_root() -> Path:
    """``$XDG_CACHE_HOME/twray/numba`` (``~/.cache/twray/numba`` by default)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "twray" / "numba"


def configure(environ=os.environ) -> str | None:
    """Point Numba's cache at the directory of the current sources; returns it (None: left as is,
    because the user set NUMBA_CACHE_DIR or no cache directory can be written)."""
    if environ.get("NUMBA_CACHE_DIR"):
        return None
    try:
        root = cache_root()
        target = root / sources_key()
        target.mkdir(parents=True, exist_ok=True)
        os.utime(target)
        others = sorted((p for p in root.iterdir() if p.is_dir() and p != target),
                        key=lambda p: p.stat().st_mtime, reverse=True)
        for old in others[KEEP:]:
            shutil.rmtree(old, ignore_errors=True)
    except OSError:
        return None
    environ["NUMBA_CACHE_DIR"] = str(target)
    config = sys.modules.get("numba.core.config")
    if config is not None:  # Numba imported first: its kernels are not yet decorated, set it there too
        config.CACHE_DIR = str(target)
    return str(target)
