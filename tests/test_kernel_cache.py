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
