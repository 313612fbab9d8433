"""The floors of lidarops (CONTRIBUTING.md, "Where things go"): every import points down, no file imports
another package's private name, no import cycle. Read from the source with ``ast`` (imports inside functions
and the module paths of lazy-attribute tables included), so nothing is imported to check it."""
from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "lidarops"

#: what each package may import besides the ground floor (lidarops' top-level modules): the floors
#: ops -> sparse / stream -> sscater / compat -> models, and ops -> data -> eval, with train on the ground
#: floor alone; cli is the one place that joins train, models, data and eval; query sits under cli.
ALLOWED = {
    "ops": set(),
    "sparse": {"ops"},
    "stream": {"ops"},
    "sscater": {"ops", "sparse", "stream"},
    "compat": {"ops", "sparse", "stream"},
    "data": {"ops"},
    "eval": {"ops", "data"},
    "train": set(),
    "models": {"ops", "sparse", "stream", "sscater"},
    "query": {"ops", "sparse", "stream", "sscater", "data", "eval", "models"},
    "cli": {"ops", "sparse", "stream", "sscater", "compat", "data", "eval", "train", "models", "query"},
}
#: ground-floor files allowed to name the packages above them, and why
GROUND_EXCEPTIONS = {
    "lidarops": "the package face: a lazy table of the ops' names",
    "lidarops._moved": "the table of moved names (0.1 paths) and where they went",
    "lidarops.extension": "loading the library registers each package's fake kernels (_registrations)",
    "lidarops.__main__": "python -m lidarops runs the command line",
}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _package(module: str) -> str:
    """The package a module belongs to ("" for the ground floor: lidarops' top-level modules)."""
    parts = module.split(".")
    if len(parts) >= 2 and (ROOT / parts[1]).is_dir():
        return parts[1]
    return ""


def _resolve(node: ast.ImportFrom, module: str, is_package: bool) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".")
    if not is_package:
        base = base[:-1]
    base = base[:len(base) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def _imports(path: Path):
    """(imported module, names, line, top_level) for every import of a file, and the module paths named by
    the strings of lazy-attribute tables (dict literals, arguments of ``lazy_attributes`` and the like)."""
    module = _module_name(path)
    tree = ast.parse(path.read_text(), str(path))
    top = {id(n) for n in tree.body}
    # strings count as imports where lazy tables keep them: dict literals and the arguments of the lazy helpers
    lazy = set()
    for node in ast.walk(tree):
        name = getattr(getattr(node, "func", None), "attr", None) or getattr(getattr(node, "func", None), "id", None)
        if isinstance(node, ast.Dict) or (isinstance(node, ast.Call) and name in LAZY_CALLS):
            lazy |= {id(c) for c in ast.walk(node) if isinstance(c, ast.Constant)}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                out.append((alias.name, [], node.lineno, id(node) in top))
        elif isinstance(node, ast.ImportFrom):
            target = _resolve(node, module, path.name == "__init__.py")
            out.append((target, [a.name for a in node.names], node.lineno, id(node) in top))
        elif id(node) in lazy and isinstance(node.value, str) and node.value.startswith("lidarops.") \
                and all(p.isidentifier() for p in node.value.split(".")):
            out.append((node.value, [], node.lineno, False))
    return [(m, n, line, t) for m, n, line, t in out if m == "lidarops" or m.startswith("lidarops.")]


FILES = sorted(ROOT.rglob("*.py"))
LAZY_CALLS = {"lazy_attributes", "moved_attributes", "import_module"}


def _edges():
    for path in FILES:
        src = _module_name(path)
        for target, names, line, top in _imports(path):
            yield path, src, target, names, line, top


def test_every_package_is_in_the_table():
    packages = {p.name for p in ROOT.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert packages == set(ALLOWED) - {p for p in ALLOWED if not (ROOT / p).is_dir()}, \
        f"packages without floor rules: {sorted(packages - set(ALLOWED))}"


def test_imports_point_down():
    wrong = []
    for path, src, target, names, line, _ in _edges():
        s, t = _package(src), _package(target)
        targets = {t} if t or target != "lidarops" else set()
        # `from lidarops import x`: x may be a package
        targets |= {n for n in names if target == "lidarops" and (ROOT / n).is_dir()}
        for t in targets:
            if not t or t == s:
                continue
            if not s:
                if src in GROUND_EXCEPTIONS:
                    continue
                wrong.append(f"{path.relative_to(ROOT.parent)}:{line}: the ground floor imports {target}")
            elif t not in ALLOWED[s]:
                wrong.append(f"{path.relative_to(ROOT.parent)}:{line}: {s} imports {t} ({target})")
    assert not wrong, "imports that point up or sideways:\n" + "\n".join(wrong)


def test_no_private_names_across_packages():
    wrong = []
    for path, src, target, names, line, _ in _edges():
        s, t = _package(src), _package(target)
        if not t or t == s:
            continue  # the ground floor's private helpers (_lazy, _checks, _progress, _moved) serve every package
        if src == "lidarops.extension" and target.endswith("._registrations"):
            continue
        private = [p for p in target.split(".")[2:] if p.startswith("_")] + [n for n in names if n.startswith("_")]
        if private:
            wrong.append(f"{path.relative_to(ROOT.parent)}:{line}: {src} uses {target}: {private}")
    assert not wrong, "private names used from another package:\n" + "\n".join(wrong)


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> list[str] | None:
        state[n] = 1
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if state.get(m) == 1:
                return stack[stack.index(m):] + [m]
            if m not in state and (found := visit(m)):
                return found
        state[n] = 2
        stack.pop()
        return None

    for n in sorted(graph):
        if n not in state and (found := visit(n)):
            return found
    return None


def test_no_cycle_between_packages():
    graph: dict[str, set[str]] = {}
    for _, src, target, names, _, _ in _edges():
        s, t = _package(src), _package(target)
        if s and t and s != t:
            graph.setdefault(s, set()).add(t)
    assert _cycle(graph) is None, f"packages import each other: {' -> '.join(_cycle(graph))}"


def test_no_cycle_between_modules_at_import_time():
    """Module-level imports (those that run when a module is imported) form no cycle."""
    modules = {_module_name(p) for p in FILES}
    graph: dict[str, set[str]] = {}
    for _, src, target, names, _, top in _edges():
        if not top:
            continue
        hits = {target} if target in modules else set()
        hits |= {f"{target}.{n}" for n in names if f"{target}.{n}" in modules}
        for h in hits - {src}:
            if not src.startswith(h + "."):  # a package's __init__ runs before its modules anyway
                graph.setdefault(src, set()).add(h)
    cycle = _cycle(graph)
    assert cycle is None, f"modules import each other at import time: {' -> '.join(cycle)}"


def test_the_checks_can_fail():
    """The checker sees an upward import, a private name and a cycle when there is one."""
    assert _package("lidarops.ops.boxes") == "ops" and _package("lidarops.config") == ""
    assert "models" not in ALLOWED["sscater"] and "data" not in ALLOWED["models"]
    assert _cycle({"a": {"b"}, "b": {"a"}}) == ["a", "b", "a"] and _cycle({"a": {"b"}}) is None


def test_import_lidarops_stays_light():
    """``import lidarops`` (and of the data floor) loads no torch and no compiled library."""
    import subprocess

    code = ("import sys, lidarops, lidarops.data, lidarops.models, lidarops.config, lidarops.conventions; "
            "print(sorted(m for m in ('torch', 'lidarops._C', 'lidarops.models.pointpillars') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.parametrize("old", sorted(__import__("lidarops._moved", fromlist=["MOVED_MODULES"]).MOVED_MODULES))
def test_moved_modules_still_import_with_a_warning(old):
    """Every module path of lidarops 0.1 that moved imports for one more release, with one warning."""
    import importlib
    import warnings

    sys.modules.pop(old, None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        module = importlib.import_module(old)
    assert any(issubclass(w.category, DeprecationWarning) and old in str(w.message) for w in caught)
    from lidarops._moved import MOVED_MODULES

    public = [n for n in dir(importlib.import_module(MOVED_MODULES[old][0])) if not n.startswith("_")]
    assert public and getattr(module, public[0]) is getattr(importlib.import_module(MOVED_MODULES[old][0]), public[0])
