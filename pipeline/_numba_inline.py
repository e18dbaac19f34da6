"""Numba's IR inliner without its quadratic copies: the same compiled code, compiled sooner.

For every ``inline="always"`` call site, Numba (0.59 to at least 0.68) copies the callee's IR
twice, block by block, each block with a ``copy.deepcopy`` of its own
(``InlineWorker.inline_ir``'s ``copy_ir``).  Every variable holds its function's scope, and the
scope every variable of the function, so each block's copy copies the whole scope again: a
callee of B blocks and V variables costs about 2·B·V copies at each site.  The wood's kernels
inline nested helpers with hundreds of blocks at each site, and these copies were about two
fifths of compiling them (docs/performance.md#compiling-the-kernels; upstream: numba/numba#8989,
NVIDIA/numba-cuda#688).

:func:`apply` makes each site copy the callee's blocks once, with one memo (the scope copied
once, shared by the copied blocks, as the original blocks share theirs), and hands that copy to
Numba's own ``inline_ir`` with its copies turned into no-ops.  The second copy was the
unmutated callee IR that ``inline_ir`` returns, which both of its callers in Numba discard (the
IR they pass is cached, or built afresh for the site, so it is never mutated here).  The inlined
IR, and so the compiled code, is the same: ``tests/test_numba_inline.py`` compares them.

:func:`install` (run when :mod:`pipeline` is imported) applies it once Numba's inliner module
has been imported, so a command that never compiles never imports it; and only where Numba's
``inline_ir`` still has the two copies this replaces, otherwise Numba is left as it is.
"""

from __future__ import annotations

import copy
import importlib
import importlib.machinery
import sys
import threading

# What inline_ir's source must hold for this to replace it: its per-block deepcopy, done twice.
_PATTERN = ("new_block = copy.deepcopy(the_ir.blocks[block_label])", "callee_ir_original = copy_ir(callee_ir)")
_state = threading.local()
_applied = None  # (the InlineWorker class, its own inline_ir) once applied
MODULE = "numba.core.inline_closurecall"


class _CopyInPlace:
    """Stands for the ``copy`` module inside Numba's inliner while it inlines a copy made here:
    ``deepcopy`` hands back what it is given (the blocks are already this site's own)."""

    def __getattr__(self, name):
        return getattr(copy, name)

    @staticmethod
    def deepcopy(x, memo=None):
        if getattr(_state, "active", False):
            return x
        return copy.deepcopy(x, memo)


def _fresh(ir):
    """``ir`` with its blocks copied in one ``deepcopy`` (one memo: one scope copy for all)."""
    out = ir.copy()
    out.blocks = copy.deepcopy(ir.blocks)
    return out


def applicable() -> bool:
    """Whether Numba's inliner has the copies :func:`apply` replaces."""
    import inspect

    try:
        icc = importlib.import_module(MODULE)  # may apply it (install's hook)
        src = inspect.getsource(_applied[1] if _applied is not None else icc.InlineWorker.inline_ir)
    except (ImportError, AttributeError, OSError, TypeError):
        return False
    return all(p in src for p in _PATTERN)


def apply() -> bool:
    """Replace ``InlineWorker.inline_ir`` as the module docstring says; True if it is (now or
    before).  Idempotent."""
    global _applied
    if _applied is not None:
        return True
    if not applicable():
        return False
    icc = sys.modules[MODULE]
    own = icc.InlineWorker.inline_ir

    def inline_ir(self, caller_ir, block, i, callee_ir, callee_freevars, arg_typs=None):
        mine = _fresh(callee_ir)
        before = getattr(_state, "active", False)
        _state.active = True
        try:
            return own(self, caller_ir, block, i, mine, callee_freevars, arg_typs=arg_typs)
        finally:
            _state.active = before

    icc.copy = _CopyInPlace()
    icc.InlineWorker.inline_ir = inline_ir
    _applied = (icc.InlineWorker, own)
    return True


def restore() -> None:
    """Numba's inliner as it was (for tests that compare both)."""
    global _applied
    if _applied is None:
        return
    icc = sys.modules[MODULE]
    cls, own = _applied
    cls.inline_ir = own
    icc.copy = copy
    _applied = None


class _OnImport:
    """A finder on ``sys.meta_path``: finds Numba's inliner module as the path finder would, and
    applies the patch once that module has run (any other module: left to the other finders)."""

    def find_spec(self, name, path, target=None):
        if name != MODULE:
            return None
        sys.meta_path.remove(self)
        spec = importlib.machinery.PathFinder.find_spec(name, path, target)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            apply()

        spec.loader.exec_module = exec_module
        return spec


def install() -> None:
    """Apply the patch now if Numba's inliner is imported, else as soon as it is."""
    if MODULE in sys.modules:
        apply()
    elif not any(isinstance(f, _OnImport) for f in sys.meta_path):
        sys.meta_path.insert(0, _OnImport())
