"""Numba's inliner with one copy of the callee a site (pipeline/_numba_inline.py): the same
compiled code, applied only where Numba still has the copies it replaces."""

import json
import subprocess
import sys

import pytest

from pipeline import _numba_inline

# Nested inline="always" helpers with loops, branches, tuples and a callee inlined at several
# sites, compiled in a fresh process: the LLVM IR and the machine code, hashed.
KERNELS = """
import hashlib, json, re, sys
import numpy as np
from numba import njit

@njit(inline="always")
def leaf(a, i):
    s = 0.0
    for k in range(i):
        if a[k] > 0.5:
            s += a[k] * k
        else:
            s -= np.sqrt(a[k] + 1.0)
    return s, i + 1

@njit(inline="always")
def mid(a, n):
    t, m = leaf(a, n)
    u, _ = leaf(a, m - 1)
    return t * u if t > u else t - u

@njit
def top(a):
    acc = 0.0
    for j in range(1, a.size):
        acc += mid(a, j) + mid(a, a.size - j)
    return acc

value = top(np.linspace(0.0, 1.0, 9))
sig = top.signatures[0]
# Addresses of Python objects and hashes of constants in symbol names vary from process to process.
h = lambda s: hashlib.sha256(re.sub(r"-?\\d{9,}", "N", re.sub(r"0x[0-9a-f]{6,}", "A", s)).encode()).hexdigest()
applied = getattr(sys.modules.get("pipeline._numba_inline"), "_applied", None) is not None
print(json.dumps({"value": value.hex(), "llvm": h(top.inspect_llvm(sig)), "asm": h(top.inspect_asm(sig)),
                  "applied": applied}))
"""


def _compiled(prelude: str) -> dict:
    out = subprocess.run([sys.executable, "-c", prelude + KERNELS], check=True, capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not _numba_inline.applicable(), reason="this Numba's inliner has no copies to replace")
def test_inlining_with_one_copy_compiles_the_same_code():
    # `import pipeline` installs the patch before Numba is imported; it applies once Numba's
    # inliner module is (nothing is compiled before then).
    patched = _compiled("import pipeline, sys\nassert 'numba.core.inline_closurecall' not in sys.modules\n")
    plain = _compiled("")
    assert patched["applied"] and not plain["applied"]
    assert patched == {**plain, "applied": True}


def test_an_inliner_without_those_copies_is_left_as_it_is(monkeypatch):
    from numba.core import inline_closurecall as icc

    was = _numba_inline._applied is not None
    _numba_inline.restore()
    try:
        def inline_ir(self, caller_ir, block, i, callee_ir, callee_freevars, arg_typs=None):
            return None  # a future Numba's inliner, without the per-block deepcopy

        monkeypatch.setattr(icc.InlineWorker, "inline_ir", inline_ir)
        assert not _numba_inline.applicable()
        assert not _numba_inline.apply()
        assert icc.InlineWorker.inline_ir is inline_ir and icc.copy.deepcopy is __import__("copy").deepcopy
    finally:
        monkeypatch.undo()
        if was:
            assert _numba_inline.apply()
