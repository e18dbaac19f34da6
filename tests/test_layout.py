"""The package's structure: lower floors never import higher ones, no import cycles, no private
name used across packages, files of one concept (the rules of docs/architecture.md)."""

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent / "pipeline"

# Floors, bottom first: a module imports only its own floor and those below.
FLOORS = [
    {"pipeline", "pipeline.versions", "pipeline.params", "pipeline.rng", "pipeline._intrinsics", "pipeline._kernel_cache",
     "pipeline._numba_inline",
     "pipeline._cauchy", "pipeline.lru",
     "pipeline.cache", "pipeline.progress", "pipeline.analysis", "pipeline.summary", "pipeline.geometry_stats",
     "pipeline.provenance", "pipeline.publish", "pipeline.runlog"},
    {"pipeline.microstructure"},
    {"pipeline.optics"},
    {"pipeline.limits", "pipeline.request", "pipeline.study", "pipeline.camera", "pipeline.wave"},
    {"pipeline.result_sets", "pipeline.figures", "pipeline.effects", "pipeline.report", "pipeline.report_tables", "pipeline.report_source",
     "pipeline.report_geometry", "pipeline.report_wave", "pipeline.report_scans", "pipeline.inventory",
     "pipeline.trace_job", "pipeline.generate_job",
     "pipeline.cluster", "pipeline.design"},
    {"pipeline.cli", "pipeline.__main__"},
]
MAX_LINES = 650  # one concept a file: about 600 lines at most


def _modules() -> dict[str, pathlib.Path]:
    out = {}
    for f in ROOT.rglob("*.py"):
        parts = f.relative_to(ROOT.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = f
    return out


MODULES = _modules()


def _imports(name: str, path: pathlib.Path):
    """(imported module, imported name or None) of every import in ``name``, inside functions too."""
    is_package = path.name == "__init__.py"
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if is_package else name.split(".")[:-1]
                base = base[:len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            for alias in node.names:
                full = f"{mod}.{alias.name}"
                yield (full, None) if full in MODULES else (mod, alias.name)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, None


EDGES = {m: {t for t, _ in _imports(m, p) if t in MODULES and t != m} for m, p in MODULES.items()}


def _floor(module: str) -> int:
    for level, names in enumerate(FLOORS):
        if module in names or any(module.startswith(n + ".") for n in names if n != "pipeline"):
            return level
    raise AssertionError(f"{module} is on no floor: add it to FLOORS")


def test_every_module_has_a_floor_and_imports_nothing_above_it():
    upward = [f"{m} (floor {_floor(m)}) imports {t} (floor {_floor(t)})"
              for m, targets in EDGES.items() for t in targets if _floor(t) > _floor(m)]
    assert not upward, "\n".join(upward)


def test_no_import_cycle():
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for t in sorted(EDGES[m]):
            if state.get(t) == 1:
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(t):] + [t]))
            if t not in state:
                visit(t)
        stack.pop()
        state[m] = 2

    for m in sorted(MODULES):
        if m not in state:
            visit(m)


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _reaches_in(m: str, t: str, n: str | None) -> bool:
    """Whether module ``m`` importing ``n`` from module ``t`` takes something private of another
    package: a private name, or any name of a private module (``from ..microstructure._constants
    import X`` reaches in as much as ``from ..microstructure.surface import _x``)."""
    return (m.split(".")[:2] != t.split(".")[:2]
            and (_private(n or "") or any(_private(part) for part in t.split(".")[2:])))


def test_no_private_name_is_imported_across_packages():
    assert _reaches_in("pipeline.optics.trace", "pipeline.microstructure._constants", "PITCH")
    assert _reaches_in("pipeline.optics.trace", "pipeline.microstructure.surface", "_row")
    assert not _reaches_in("pipeline.microstructure.surface", "pipeline.microstructure._constants", "PITCH")
    assert not _reaches_in("pipeline.optics.trace", "pipeline.microstructure.surface", "evaluate")
    crossing = [f"{m} imports {t}.{n}" for m, p in MODULES.items() for t, n in _imports(m, p)
                if t in MODULES and _reaches_in(m, t, n)]
    assert not crossing, "\n".join(crossing)


@pytest.mark.parametrize("path", sorted(ROOT.rglob("*.py")), ids=lambda p: str(p.relative_to(ROOT.parent)))
def test_files_hold_one_concept_and_cite_only_the_repository(path):
    text = path.read_text()
    assert text.count("\n") <= MAX_LINES, f"{path} has {text.count(chr(10))} lines: split it by concept"
    for outside in ("SPEC.md", "GENERATOR.md", "DESIGN.md"):
        assert outside not in text, f"{path} cites {outside}, which is not in this repository: cite docs/"


def test_the_layout_check_sees_the_package():
    # A check that finds no modules or no edges would pass vacuously.
    assert {"pipeline.optics.trace", "pipeline.study.plan", "pipeline.cli"} <= set(MODULES)
    assert "pipeline.versions" in EDGES["pipeline.provenance"]
    assert sum(len(t) for t in EDGES.values()) > 150


def _functions():
    """(module path, function, lines, a Numba kernel) of every function of the package."""
    for path in sorted(ROOT.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                kernel = any(getattr(d.func if isinstance(d, ast.Call) else d, "id", None) in ("njit", "jit")
                             or getattr(d.func if isinstance(d, ast.Call) else d, "attr", None) in ("njit", "jit")
                             for d in node.decorator_list)
                yield path.relative_to(ROOT.parent), node.name, node.end_lineno - node.lineno + 1, kernel


MAX_FUNCTION_LINES = 120  # outside the Numba kernels (a kernel is one loop the compiler must see whole)
MAX_COMMAND_LINES = 40  # a command parses its arguments, calls one library function and prints


def test_functions_are_short_and_commands_shorter():
    functions = list(_functions())
    assert len(functions) > 500 and any(k for *_, k in functions)  # the check sees the package and its kernels
    long = [f"{p}:{name} has {n} lines" for p, name, n, kernel in functions
            if (not kernel and n > MAX_FUNCTION_LINES) or (name.startswith("cmd_") and n > MAX_COMMAND_LINES)]
    assert not long, "split them by what they do:\n" + "\n".join(long)


def test_the_architecture_page_lists_every_module_and_only_modules_that_exist():
    """docs/architecture.md cannot drift: its module listing names every module of the package, its
    floor table every top-level module and package on its floor, and it names no file that is gone."""
    import re

    text = (ROOT.parent / "docs" / "architecture.md").read_text()
    listing = text.split("## Modules", 1)[1].split("```")[1]
    stems = {p.stem for p in ROOT.rglob("*.py") if p.stem not in ("__init__", "__main__")}
    missing = sorted(s for s in stems if not re.search(rf"(?<![\w.]){re.escape(s)}\b", listing))
    assert not missing, f"docs/architecture.md does not list {missing}"
    gone = sorted(f for f in re.findall(r"(\w+)\.py", listing) if f not in stems)
    assert not gone, f"docs/architecture.md lists files that do not exist: {gone}"
    table = {int(m[1]): m[2] for m in re.finditer(r"^\| (\d) \| (.+?) \|", text, re.M)}
    for level, names in enumerate(FLOORS):
        for name in names:
            if name == "pipeline":
                continue
            short = name.removeprefix("pipeline.")
            assert re.search(rf"`{re.escape(short)}/?`", table[level]), f"{short} is not on floor {level} of the table"
