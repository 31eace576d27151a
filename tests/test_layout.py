"""The package's layout: five parts over a shared base, imports point one way (docs/architecture.md).

app -> api -> fitting -> model -> rendering -> base: a module imports from its own part and the parts below it,
never above.
Function-level imports count: a lazy import is still a dependency.
"""

import ast
import importlib.util
from pathlib import Path

import matfit

PACKAGE = Path(matfit.__file__).resolve().parent
PARTS = ("base", "rendering", "model", "fitting", "api", "app")  # lowest first
# `python -m matfit` runs the command line, and the package `matfit` lists the public API (`matfit.api`'s names) that
# a user's script calls: they sit above everything.
ENTRY_POINTS = {"matfit.__main__": "app", "matfit": "app"}
# Import circles that are known and named; each must still exist (the last test), so a fixed one is removed here.
ALLOWED_CIRCLES: tuple[set[str], ...] = ()


def modules() -> dict[str, Path]:
    """Returns every module of the package by dotted name (packages by their __init__)."""
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def part(name: str) -> str:
    """Returns the part a module belongs to: the subpackage under matfit, or "base"."""
    if name in ENTRY_POINTS:
        return ENTRY_POINTS[name]
    pieces = name.split(".")
    return pieces[1] if len(pieces) > 2 or (len(pieces) == 2 and pieces[1] in PARTS) else "base"


def imported(path: Path, known: dict[str, Path]) -> set[str]:
    """Returns the matfit modules a module imports anywhere in it (`from a import b` counts a.b if it is a module)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names if alias.name.split(".")[0] == "matfit")
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"{path}: relative import; import matfit modules by their full name"
            if node.module and node.module.split(".")[0] == "matfit":
                for alias in node.names:
                    inner = f"{node.module}.{alias.name}"
                    names.add(inner if inner in known else node.module)
    return names


def graph() -> dict[str, set[str]]:
    known = modules()
    return {name: imported(path, known) - {name} for name, path in known.items()}


def test_every_module_lies_in_the_base_or_one_part():
    for name, path in modules().items():
        assert path.parent == PACKAGE or name.split(".")[1] in PARTS[1:], f"{path} lies outside the five parts"


def test_imports_point_from_app_to_api_to_fitting_to_model_to_rendering_to_the_base():
    known = modules()
    wrong = [
        f"{name} ({part(name)}) imports {target} ({part(target)})"
        for name, targets in graph().items()
        for target in sorted(targets)
        if target in known and PARTS.index(part(target)) > PARTS.index(part(name))
    ]
    assert wrong == [], "imports that point up: " + "; ".join(wrong)


def circles(edges: dict[str, set[str]]) -> list[set[str]]:
    """Returns the strongly connected components of more than one module (Tarjan's algorithm)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(edges.get(node, ())):
            if target not in edges:
                continue
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = set()
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.add(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(component)

    for node in sorted(edges):
        if node not in index:
            visit(node)
    return found


def test_no_import_circles_but_the_named_ones():
    found = circles(graph())
    assert [circle for circle in found if circle not in ALLOWED_CIRCLES] == []
    assert all(circle in found for circle in ALLOWED_CIRCLES), "a named circle is gone: remove it from ALLOWED_CIRCLES"


def test_the_circle_finder_finds_a_circle_and_only_it():
    edges = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert circles(edges) == [{"a", "b", "c"}]


def test_each_part_says_what_it_holds_and_what_it_may_import():
    for name in PARTS[1:]:
        init = PACKAGE / name / "__init__.py"
        tree = ast.parse(init.read_text(encoding="utf-8"))
        docstring = ast.get_docstring(tree) or ""
        assert "may import" in docstring, f"{init}: its docstring says what the part may import"
        assert len(tree.body) == 1, f"{init}: only the docstring (modules are imported by their full name)"
        assert importlib.util.find_spec(f"matfit.{name}") is not None


def test_no_module_of_the_public_api_is_over_400_lines():
    lengths = {path.name: len(path.read_text(encoding="utf-8").splitlines()) for path in (PACKAGE / "api").glob("*.py")}
    assert len(lengths) >= 5 and max(lengths.values()) <= 400, lengths
