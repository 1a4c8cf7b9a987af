"""The package layout of docs/architecture.md, enforced on the source (parsed with ``ast``).

- Import rules between the packages of ``src/seathru`` (module-level and lazy imports inside
  functions, ``TYPE_CHECKING`` blocks and ``importlib.import_module("seathru....")`` included).
- Step modules stay thin: at most ``MAX_STEP_LINES`` lines unless listed with a reason.
- No two public top-level functions or classes with one name in different modules.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import pytest

from tests.conftest import REPO_ROOT

PACKAGE_ROOT = REPO_ROOT / "src" / "seathru"
DOMAIN = ("sim", "radiometry", "geometry", "nerf", "eval")

# What each part of the package must not import (parts: the subpackages, and the top-level
# modules cli, settings, errors). The reasons are in docs/architecture.md.
FORBIDDEN: dict[str, set[str]] = {
    "sim": {"io", "steps", "cli", "nerf"},
    "nerf": {"io", "steps", "cli", "sim"},
    "eval": {"io", "steps", "cli", "sim", "nerf"},
    "radiometry": {"io", "steps", "cli", "sim", "nerf", "eval", "geometry"},
    "geometry": {"io", "steps", "cli", "sim", "nerf", "eval", "radiometry"},
    "io": {"steps", "cli"},
    "errors": {"sim", "nerf", "eval", "radiometry", "geometry", "io", "steps", "cli", "settings"},
    "settings": {"cli"},
    "steps": {"cli"},
    "cli": set(),
}
# Exceptions to FORBIDDEN, each with its reason: (importing part, imported module) -> why.
ALLOWED_IMPORTS: dict[tuple[str, str], str] = {}
# Only these parts may import a step module (seathru.steps.<step>); the steps package itself
# (its STEP_ORDER) may also be imported by the step modules.
STEP_MODULE_IMPORTERS = {"cli", "settings"}
STEP_PACKAGE_IMPORTERS = {"cli", "settings", "steps"}

MAX_STEP_LINES = 170
# step module -> why it may be longer (agreed with the lead); empty: none may.
LONG_STEP_MODULES: dict[str, str] = {}

#: A module longer than this holds more than one part: split it by what each part does (as
#: eval/report.py became report, report_records, report_warnings and report_tracks).
MAX_MODULE_LINES = 800

# Public names every step module defines by convention.
SHARED_PUBLIC_NAMES = {"add_arguments", "run", "main", "Settings"}


def _modules() -> dict[str, Path]:
    """Dotted module name -> file, for every module of src/seathru."""
    modules = {}
    for path in sorted(PACKAGE_ROOT.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE_ROOT.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        modules[".".join(parts)] = path
    return modules


MODULES = _modules()


def _part(module: str) -> str:
    """The part of the package a dotted module belongs to: 'nerf', 'cli', ... or 'seathru'."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "seathru"


def _resolve_from(module: str, is_package: bool, node: ast.ImportFrom) -> str | None:
    if node.level == 0:
        return node.module
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[:len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _dynamic_import(node: ast.Call) -> str | None:
    """The module of ``importlib.import_module("seathru.x")`` / f"seathru.steps.{name}"."""
    func = node.func
    name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
    if name not in ("import_module", "__import__") or not node.args:
        return None
    arg = node.args[0]
    if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
        return arg.value
    if isinstance(arg, ast.JoinedStr) and arg.values and isinstance(arg.values[0], ast.Constant):
        prefix = str(arg.values[0].value)
        # f"seathru.steps.{name}": some module of seathru.steps
        return prefix.rstrip(".") + (".*" if prefix.endswith(".") else "")
    return None


def imports_of(path: Path, module: str) -> list[tuple[int, str]]:
    """(line, imported seathru module) for every import in the file, lazy ones included."""
    tree = ast.parse(path.read_text(), filename=str(path))
    is_package = path.name == "__init__.py"
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = _resolve_from(module, is_package, node)
            if base is None:
                continue
            for alias in node.names:
                candidate = f"{base}.{alias.name}"
                # `from seathru import settings` imports the module seathru.settings
                found.append((node.lineno, candidate if candidate in MODULES else base))
        elif isinstance(node, ast.Call):
            target = _dynamic_import(node)
            if target:
                found.append((node.lineno, target))
    return sorted({(line, name) for line, name in found
                   if name == "seathru" or name.startswith("seathru.")})


def _shown(path: Path) -> str:
    return str(path.relative_to(REPO_ROOT)) if path.is_relative_to(REPO_ROOT) else str(path)


def _violations(module: str, path: Path) -> list[str]:
    part = _part(module)
    bad = []
    for line, target in imports_of(path, module):
        where = f"{_shown(path)}:{line} imports {target.removesuffix('.*')}"
        target_part = _part(target)
        if target_part == part:
            if part == "steps" and target.startswith("seathru.steps.") and module != target:
                bad.append(f"{where}: a step module imports another step module "
                           "(shared code belongs in a domain package or io)")
            continue
        if (part, target.removesuffix(".*")) in ALLOWED_IMPORTS:
            continue
        if target_part in FORBIDDEN.get(part, set()):
            bad.append(f"{where}: {part} must not import {target_part}")
        elif target_part == "steps":
            is_step_module = target != "seathru.steps"
            allowed = STEP_MODULE_IMPORTERS if is_step_module else STEP_PACKAGE_IMPORTERS
            if part not in allowed:
                bad.append(f"{where}: only {', '.join(sorted(allowed))} may import "
                           f"{'a step module' if is_step_module else 'seathru.steps'}")
    return bad


def test_the_package_has_the_documented_parts():
    parts = {_part(module) for module in MODULES}
    assert set(DOMAIN) | {"io", "steps", "cli", "settings", "errors"} <= parts, sorted(parts)
    undocumented = parts - set(FORBIDDEN) - {"seathru"}
    assert not undocumented, (f"new parts {sorted(undocumented)}: add their import rules here "
                              "and in docs/architecture.md")


@pytest.mark.parametrize("package", [*DOMAIN, "io", "steps"])
def test_each_package_says_what_it_owns(package):
    init = PACKAGE_ROOT / package / "__init__.py"
    assert init.is_file(), f"{init} missing"
    docstring = ast.get_docstring(ast.parse(init.read_text()))
    assert docstring and len(docstring.split()) >= 5, f"{init}: no module docstring"


def test_imports_follow_the_architecture():
    bad = [message for module, path in MODULES.items() for message in _violations(module, path)]
    assert not bad, "import rules of docs/architecture.md broken:\n" + "\n".join(bad)


def test_the_import_checker_sees_lazy_relative_and_dynamic_imports(tmp_path):
    source = tmp_path / "seathru" / "sim" / "probe.py"
    source.parent.mkdir(parents=True)
    source.write_text(
        "import importlib\n"
        "from ..nerf import model\n"
        "def f(name):\n"
        "    from seathru.io import images\n"
        "    return importlib.import_module(f'seathru.steps.{name}')\n")
    found = sorted(name for _, name in imports_of(source, "seathru.sim.probe"))
    assert found == ["seathru.io.images", "seathru.nerf.model", "seathru.steps.*"], found
    messages = _violations("seathru.sim.probe", source)
    assert any("sim must not import nerf" in m for m in messages), messages
    assert any("sim must not import io" in m for m in messages), messages
    assert any("sim must not import steps" in m for m in messages), messages


def test_step_modules_are_thin():
    lengths = {path.stem: len(path.read_text().splitlines())
               for path in sorted((PACKAGE_ROOT / "steps").glob("*.py"))
               if path.name != "__init__.py"}
    too_long = {name: lines for name, lines in lengths.items()
                if lines > MAX_STEP_LINES and name not in LONG_STEP_MODULES}
    assert not too_long, (f"step modules over {MAX_STEP_LINES} lines (move domain logic to a "
                          f"domain package or io, or list the module in LONG_STEP_MODULES "
                          f"with a reason): {too_long}")
    stale = {name for name in LONG_STEP_MODULES if lengths.get(name, 0) <= MAX_STEP_LINES}
    assert not stale, f"LONG_STEP_MODULES lists modules that are short now: {sorted(stale)}"


def test_no_module_grows_past_a_few_parts():
    lengths = {module: len(path.read_text().splitlines()) for module, path in MODULES.items()}
    too_long = {module: lines for module, lines in lengths.items() if lines > MAX_MODULE_LINES}
    assert not too_long, (f"modules over {MAX_MODULE_LINES} lines (split each by what its "
                          f"parts do, one module a part; docs/architecture.md): {too_long}")


def public_names(path: Path) -> list[tuple[str, int]]:
    tree = ast.parse(path.read_text(), filename=str(path))
    return [(node.name, node.lineno) for node in tree.body
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))
            and not node.name.startswith("_")]


def test_no_public_name_is_defined_in_two_modules():
    where = defaultdict(list)
    for module, path in MODULES.items():
        for name, line in public_names(path):
            if name not in SHARED_PUBLIC_NAMES:
                where[name].append(f"{path.relative_to(REPO_ROOT)}:{line}")
    duplicated = {name: places for name, places in where.items() if len(places) > 1}
    assert not duplicated, ("public functions / classes defined in more than one module (one "
                            "meaning per name: rename one or share one): "
                            + "; ".join(f"{name} in {', '.join(places)}"
                                        for name, places in sorted(duplicated.items())))
