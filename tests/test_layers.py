"""Package layering, from the source (`ast`): what each subpackage may import."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "robtraj"

#: subpackage → robtraj subpackages it must not import
FORBIDDEN = {
    "jax_ops": {"*"},
    "model": {"estimate", "analysis", "report", "cli", "sim", "importers", "acquisition"},
    "estimate": {"analysis", "report", "cli"},
}


#: the modules of `robtraj.estimate` a recording passes through in `calibration.fit`, in
#: order (`fit` calls a step of each, from `_calib_setup` on): each imports only modules
#: before it, so that the data flow one way
FIT_STEPS = (
    "_calib_parameters",
    "_calib_data",
    "_calib_init",
    "_calib_problem",
    "_calib_clusters",
    "_calib_setup",
    "_calib_solves",
    "_calib_residuals",
    "_calib_uncertainty",
    "_next_poses",
    "_calib_result",
    "calibration",
)


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> list[tuple[str, tuple[str, ...]]]:
    """Absolute robtraj modules imported by `path`, with the names taken from them."""
    mod = _module_name(path)
    package = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [(a.name, ()) for a in node.names if a.name.split(".")[0] == "robtraj"]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] == "robtraj":
                out.append((target, tuple(a.name for a in node.names)))
    return out


def _files():
    return sorted(p for p in ROOT.rglob("*.py") if "__pycache__" not in p.parts)


def _subpackage(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def test_the_import_parser_sees_relative_and_absolute_imports(tmp_path):
    pkg = ROOT / "estimate" / "calibration.py"
    targets = {t for t, _ in _imports(pkg)}
    assert "robtraj.estimate._calib_problem" in targets and "robtraj.model" in targets


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_lower_layers_do_not_import_higher_ones(package):
    bad = []
    for path in (ROOT / package).rglob("*.py"):
        for target, _ in _imports(path):
            sub = _subpackage(target)
            if sub == package:
                continue
            if "*" in FORBIDDEN[package] or sub in FORBIDDEN[package]:
                bad.append(f"{_module_name(path)} imports {target}")
    assert not bad, bad


def test_the_steps_of_a_calibration_import_only_earlier_steps():
    order = {f"robtraj.estimate.{m}": k for k, m in enumerate(FIT_STEPS)}
    bad = []
    for k, step in enumerate(FIT_STEPS):
        for target, names in _imports(ROOT / "estimate" / f"{step}.py"):
            modules = [f"{target}.{n}" for n in names if f"{target}.{n}" in order] or [target]
            bad += [f"{step} imports {m}" for m in modules if order.get(m, -1) >= k]
    assert not bad, bad


def test_no_private_imports_across_packages():
    """A module outside a subpackage uses only its public names: no `_module` of it and
    no `_name` from it."""
    bad = []
    for path in _files():
        here = _subpackage(_module_name(path))
        for target, names in _imports(path):
            if _subpackage(target) == here or not _subpackage(target):
                continue
            private_module = any(p.startswith("_") for p in target.split(".")[2:])
            private_name = [n for n in names if n.startswith("_")]
            if private_module or private_name:
                bad.append(f"{_module_name(path)}: from {target} import {', '.join(names)}")
    assert not bad, "\n".join(sorted(set(bad)))


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Cycles found by a depth-first search (one per back edge)."""
    state: dict[str, int] = {}
    found = []

    def visit(m, stack):
        state[m] = 1
        for d in sorted(graph.get(m, ())):
            if state.get(d) == 1:
                found.append(stack[stack.index(d) :] + [d])
            elif d not in state:
                visit(d, [*stack, d])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    return found


def test_the_cycle_search_finds_cycles():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == [["a", "b", "c", "a"]]
    assert _cycles({"a": {"b", "c"}, "b": {"c"}, "c": set()}) == []


def test_no_import_cycles_between_modules():
    mods = {_module_name(p) for p in _files()}
    graph: dict[str, set[str]] = {}
    for path in _files():
        me = _module_name(path)
        deps = set()
        for target, names in _imports(path):
            hits = [f"{target}.{n}" for n in names if f"{target}.{n}" in mods]
            deps |= set(hits) if hits else ({target} if target in mods else set())
        graph[me] = deps - {me}
    # a package's __init__ importing its own modules is how it re-exports them
    for m in graph:
        graph[m] = {d for d in graph[m] if not (m.startswith(d + ".") and d != "robtraj")}
    assert not _cycles(graph), _cycles(graph)
