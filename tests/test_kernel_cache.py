"""Compiled kernels live in a cache directory keyed by the kernels' sources."""

import os
import subprocess
import sys

from pipeline import _kernel_cache as kc


def _package(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "kern.py").write_text("from numba import njit\n@njit\ndef f(x):\n    return x + 1\n")
    (pkg / "sub" / "other.py").write_text("@intrinsic\ndef g(typingctx, x):\n    pass\n")
    (pkg / "plain.py").write_text("def h():\n    return 2\n")
    return pkg


def test_key_follows_kernel_sources_only(tmp_path):
    pkg = _package(tmp_path)
    key = kc.sources_key(pkg)
    (pkg / "plain.py").write_text("def h():\n    return 3\n")  # no kernel: same compiled code
    assert kc.sources_key(pkg) == key
    (pkg / "sub" / "other.py").write_text("@intrinsic\ndef g(typingctx, x):\n    return None\n")
    changed = kc.sources_key(pkg)
    assert changed != key
    (pkg / "sub" / "other.py").rename(pkg / "other.py")  # the same source elsewhere is another kernel
    assert kc.sources_key(pkg) not in (key, changed)


def test_user_cache_dir_wins_and_old_dirs_are_pruned(tmp_path, monkeypatch):
    env = {"NUMBA_CACHE_DIR": str(tmp_path / "mine")}
    assert kc.configure(env) is None and env["NUMBA_CACHE_DIR"] == str(tmp_path / "mine")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    root = tmp_path / "xdg" / "twray" / "numba"
    for i in range(kc.KEEP + 2):
        (root / f"old{i}").mkdir(parents=True)
        os.utime(root / f"old{i}", (1000 + i, 1000 + i))
    env = {}
    target = kc.configure(env)
    assert env["NUMBA_CACHE_DIR"] == target and target == str(root / kc.sources_key())
    left = sorted(p.name for p in root.iterdir())
    assert left == sorted([kc.sources_key()] + [f"old{i}" for i in range(2, kc.KEEP + 2)])


def test_numba_uses_the_keyed_directory(tmp_path):
    # A fresh interpreter, Numba imported before the package: its kernels still cache in the keyed directory.
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(tmp_path)
    code = ("import numba.core.config as c, pipeline, os; "
            "print(c.CACHE_DIR); print(os.environ['NUMBA_CACHE_DIR'])")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    numba_dir, env_dir = out.stdout.split()
    assert numba_dir == env_dir == str(tmp_path / "twray" / "numba" / kc.sources_key())



# Traces of every kind of generated wood and of a lattice, with `exact` and a voxel method, and the
# generator's blocks, in a fresh interpreter; it prints the kernel cache directory it used.
_WORKLOAD = """
import os
from pipeline.microstructure.model import generate_block
from pipeline.optics.media import wood_medium
from pipeline.optics.rays import square_beam
from pipeline.optics.references import reference
from pipeline.optics.settings import Optics, settings_for
from pipeline.optics.trace import trace
from pipeline.params import build_params, make_grid
for name in ("birch", "balsa"):
    p = build_params(name)
    for method in ("exact", "accurate"):
        s = settings_for(method)
        trace(wood_medium(p, seed=3, thickness_um=20.0, voxel_um=0.5, settings=s), square_beam(4, 10.0, seed=2),
              Optics(1.53, 1.52), s)
    generate_block(p, make_grid((20.0, 20.0, 20.0), 0.5, (0.0, 0.0, 0.0), p), (0, 0, 0), (8, 8, 8), seed=5)
lat = reference("tubes-hex", pitch_um=14.5, wall_um=2.0, jitter=0.1).lattice(1)
trace(lat.slab(20.0), square_beam(4, 10.0, seed=1), Optics(1.52, 1.49), settings_for("exact"))
print(os.environ["NUMBA_CACHE_DIR"])
"""


# Kernels that only the package calls, with the signatures it compiles them for: one, or two where the
# march hands them generated wood's context or a lattice's.  (Kernels the tests call from Python take
# whatever the tests pass: a Python int seed, a Fortran-ordered array.)
PACKAGE_ONLY = {
    "surface.evaluate": 1, "_surface_cells._polygon": 1, "_slice.vessel_walls": 1, "_slice._eval_bucket": 1,
    "_ray_cells.ray_slice_tables": 1, "_distortion.distortion_tile": 1,
    "_surface_march.march": 2, "_surface_march._lattice_bracket": 2, "_surface_march._before_root": 2,
}


def test_each_kernel_compiles_for_one_signature():
    # A kernel typed twice compiles twice: an argument that is a literal (a `0`, a `False`) or a
    # narrower integer where the caller's variable is first seen, or a read-only array where the
    # other callers pass writable ones.  The wood's evaluation and the march's lattice bracket each
    # cost about 20 s of a fresh install's compile so (docs/performance.md#compiling-the-kernels).
    # Every signature compiled from these sources is a file of the keyed cache directory (one folder
    # per source folder of each checkout), whichever process compiled it; the workload compiles what
    # is not there yet.  A literal type in a signature can only come from a kernel's own call: none
    # may hold one.  The kernels only the package calls hold the signatures PACKAGE_ONLY gives.
    import pickle
    import re
    from collections import Counter
    from pathlib import Path

    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    out = subprocess.run([sys.executable, "-c", _WORKLOAD], env=env, capture_output=True, text=True, check=True)
    cache = Path(out.stdout.split()[-1])
    assert cache.name == kc.sources_key()
    counts = Counter()
    literal = []
    for index in cache.rglob("*.nbi"):
        with open(index, "rb") as f:
            pickle.load(f)  # Numba's version
            _, overloads = pickle.loads(f.read())
        name = re.sub(r"-\d+\.py\d+\.nbi$", "", index.name)
        counts[name] = max(counts[name], len(overloads))
        literal += [name for key in overloads if "Literal[" in str(key[0])]
    assert not literal, literal
    assert {name: counts[name] for name in PACKAGE_ONLY} == PACKAGE_ONLY
