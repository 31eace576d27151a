"""Moves matfit's flat modules into the four subpackages of issue 38 and rewrites every reference to them.

Run once, at the repository root, on a clean git tree, with the project's Python:

    .venv/bin/python scripts/relayout.py --dry-run   # the plan: moves, renamed names, files rewritten
    .venv/bin/python scripts/relayout.py             # git mv, rewrite, write tests/test_layout.py, ruff

The layout (see PLACES below; imports point one way: app -> fit -> model -> render -> base):

    matfit/            the shared base: errors, files, interrupt, params, images, programs, edits, shipped, documents,
                       and __main__ (the entry point `python -m matfit`, allowed to import app.cli)
    matfit/render/     scene, engine (was render.py), presets, export, blender, blender_scene, blender_material
    matfit/model/      models, dataset, cluster, pipeline, train, evaluate
    matfit/fit/        methods, search (was fit.py), simplex, gradient, correct, verify, refine, sequence,
                       fitfile, report
    matfit/app/        cli, console, options, progress, serve, bench, examples

Two modules are renamed because a subpackage takes their name: `render.py` becomes `render/engine.py` and
`fit.py` becomes `fit/search.py`. Every other module keeps its name. `matfit/data` and `matfit/static` stay.

What is rewritten, in matfit/, tests/, scripts/, Makefile, pyproject.toml, .ci/, README.md and docs/:
- `from matfit import a, b` statements (parsed, not matched): each moved module is imported from its subpackage
  (`from matfit.fit import verify`); a renamed module is imported by its new name and every use of its old name in
  that file is renamed (`fit.fit(...)` -> `search.fit(...)`), unless the file binds the old or new name to something
  else, in which case it is imported `as` the old name (the report lists those files);
- dotted names anywhere (imports, `python -m matfit.examples`, monkeypatch targets, strings, prose):
  `matfit.render` -> `matfit.render.engine`, `matfit.cli` -> `matfit.app.cli`;
- `from matfit import render` inside strings (the code a child process runs) and prose: rewritten with aliases so
  the code after it still runs (`from matfit.render import engine as render`);
- paths `matfit/x.py` -> `matfit/<part>/x.py`; the bare file names `render.py`, `fit.py` in prose -> the new names;
  backticked references to a renamed module's names (`render.Renderer`) -> the new module name;
- in moved modules, `os.path.dirname(os.path.dirname(os.path.abspath(__file__)))` (the folder holding the package)
  gains one `dirname`; blender_scene's own sys.path set-up too (SPECIAL_EDITS). Any other use of `__file__` must
  name a sibling file that moves into the same subpackage, or the script refuses.

It refuses, changing nothing, when the tree is dirty, when a subpackage folder already exists, when matfit/ holds
a module or package that PLACES does not place (add it to PLACES), or when a relative import or an unknown use of
`__file__` would break. Afterwards it runs `ruff check --fix --select I` and `ruff format` on matfit, tests and
scripts (imports sort differently once they name subpackages). It stages its changes and commits nothing.
"""

from __future__ import annotations

import argparse
import ast
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

PACKAGE = "matfit"
# The parts, lowest first: a module may import from its own part and the parts before it.
PARTS = ("render", "model", "fit", "app")
BASE = (
    "__init__",
    "__main__",
    "errors",
    "files",
    "interrupt",
    "params",
    "images",
    "programs",
    "edits",
    "shipped",
    "documents",  # JSON reading and writing (branch inputfaults): params imports it
)
# Every module or package of matfit/ that moves: name -> "part" or "part.new_name".
PLACES = {
    "scene": "render",
    "render": "render.engine",
    "presets": "render",
    "export": "render",
    "blender": "render",
    "blender_scene": "render",
    "blender_material": "render",
    "models": "model",
    "dataset": "model",
    "cluster": "model",
    "pipeline": "model",
    "train": "model",
    "evaluate": "model",
    "methods": "fit",
    "fit": "fit.search",
    "simplex": "fit",
    "gradient": "fit",
    "correct": "fit",
    "verify": "fit",
    "refine": "fit",
    "sequence": "fit",
    "fitfile": "fit",
    "report": "fit",
    "cli": "app",
    "console": "app",
    "options": "app",
    "progress": "app",
    "serve": "app",
    "bench": "app",
    "examples": "app",
}
STAYING_FOLDERS = ("data", "static")  # package data: never moved
DOCSTRINGS = {
    "render": (
        "Rendering the material test scene: the scene as plain data (`scene`), the Mitsuba renderer and its child "
        "process (`engine`), the named materials (`presets`), the Mitsuba XML and Blender exports (`export`, "
        "`blender_material`) and Cycles against Mitsuba (`blender`; `blender_scene` runs inside Blender's own "
        "Python). It may import the shared base (`matfit.params`, `matfit.errors`, `matfit.images`, `matfit.files`, "
        "...) and nothing from `model`, `fit` or `app`."
    ),
    "model": (
        "The networks and what they learn from: the decoder and the nine encoders with their weights (`models`), the "
        "rendered training sets (`dataset`, rendered by a local process pool or as Ray tasks by `cluster`), the input "
        "pipeline (`pipeline`), training (`train`) and evaluation with the model card (`evaluate`). It may import "
        "`render` (training sets and references are renders of the test scene) and the shared base, never `fit` or "
        "`app`."
    ),
    "fit": (
        "Fitting the 19 parameters to a picture: the methods and their settings (`methods`), the objective and the "
        "best-of-n search of the paper's Algorithm 1 (`search`), the optimisers (`simplex`, `gradient`), Mitsuba in "
        "the loop after the search (`verify`, `correct`, `refine`), image sequences (`sequence`), a picture file end "
        "to end (`fitfile`) and the visual report (`report`). It may import `model`, `render` and the shared base, "
        "never `app`."
    ),
    "app": (
        "What a user runs: the command line (`cli`, with its shared `options`, the `console` conventions and "
        "`progress` bars), the edit-and-see page (`serve`), the benchmarks (`bench`) and the generator of the shipped "
        "example edits (`examples`). It may import every other part; nothing imports it but `matfit.__main__`."
    ),
}
# Exact edits that the general rules cannot make: (module, old text, new text), each found exactly once.
SPECIAL_EDITS = (
    (
        "blender_scene",
        '"matfit", os.path.join(_here, "__init__.py"), submodule_search_locations=[_here]',
        '"matfit", os.path.join(os.path.dirname(_here), "__init__.py"), '
        "submodule_search_locations=[os.path.dirname(_here)]",
    ),
    # The package's own files named through shipped.PACKAGE (the matfit folder) move into render/ with their module.
    ("blender", 'shipped.PACKAGE / "blender_scene.py"', 'shipped.PACKAGE / "render" / "blender_scene.py"'),
    ("export", 'shipped.PACKAGE / "blender_material.py"', 'shipped.PACKAGE / "render" / "blender_material.py"'),
)
TEXT_SUFFIXES = (".py", ".md", ".toml", ".js", ".html", ".css", ".cfg", ".ini", ".txt", ".sh", ".yml", ".yaml")
REWRITTEN = ("matfit", "tests", "scripts", ".ci", "docs", "Makefile", "pyproject.toml", "README.md")
MARK = "\x00"  # stands for "matfit" in generated imports until the text rules have run (which must skip them)

LAYOUT_TEST = '''"""The package's layout: four parts over a shared base, imports point one way (docs/architecture.md).

app -> fit -> model -> render -> base: a module imports from its own part and the parts below it, never above.
Function-level imports count: a lazy import is still a dependency.
"""

import ast
import importlib.util
from pathlib import Path

import matfit

PACKAGE = Path(matfit.__file__).resolve().parent
PARTS = ("base", "render", "model", "fit", "app")  # lowest first
ENTRY_POINTS = {"matfit.__main__": "app"}  # `python -m matfit` runs the command line: it sits above everything
# Import circles that are known and named; each must still exist (the last test), so a fixed one is removed here.
# dataset <-> cluster: `render_missing` hands its chunks to Ray (imported only for --ray), and cluster renders them
# with the dataset's own chunk renderer; breaking it means passing the executor in from the caller.
ALLOWED_CIRCLES = ({"matfit.model.dataset", "matfit.model.cluster"},)


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
        assert path.parent == PACKAGE or name.split(".")[1] in PARTS[1:], f"{path} lies outside the four parts"


def test_imports_point_from_app_to_fit_to_model_to_render_to_the_base():
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
'''


class RefusedError(Exception):
    """The tree is not in a state the script can move; the message says what to do."""


def run(*command: str) -> str:
    return subprocess.run(command, check=True, capture_output=True, text=True).stdout


def new_place(unit: str) -> tuple[str, str]:
    """Returns (part, new name) of a moved module or package."""
    place = PLACES[unit]
    return (place.split(".")[0], place.split(".")[1]) if "." in place else (place, unit)


def new_dotted(unit: str) -> str:
    part, name = new_place(unit)
    return f"{PACKAGE}.{part}.{name}"


def units(tracked: list[str]) -> dict[str, str]:
    """Returns matfit's top-level modules and packages: name -> "module" or "package"; refuses unknown folders."""
    found, odd = {}, []
    for path in tracked:
        pieces = path.split("/")
        if pieces[0] != PACKAGE or len(pieces) < 2:
            continue
        if len(pieces) == 2:
            if pieces[1].endswith(".py"):
                found[pieces[1][:-3]] = "module"
        elif pieces[1] not in STAYING_FOLDERS:
            if f"{PACKAGE}/{pieces[1]}/__init__.py" in tracked:
                found[pieces[1]] = "package"
            else:
                odd.append(f"{PACKAGE}/{pieces[1]}/")
    if odd:
        raise RefusedError(f"folders that are neither package data nor packages: {', '.join(sorted(set(odd)))}")
    return found


def check_tree(tracked: list[str], found: dict[str, str]) -> list[str]:
    """Refuses a dirty tree, existing subpackages and unplaced modules; returns notices."""
    if run("git", "status", "--porcelain", "--untracked-files=no").strip():
        raise RefusedError("the tree has uncommitted changes: commit or stash them first (git status)")
    untracked = run("git", "ls-files", "--others", "--exclude-standard", PACKAGE, "tests").split()
    if untracked:
        raise RefusedError(f"untracked files would be left behind: {', '.join(untracked)}: commit or remove them first")
    existing = [part for part in PARTS if os.path.isdir(os.path.join(PACKAGE, part))]
    existing += [path for path in ("tests/test_layout.py",) if os.path.exists(path)]
    if existing:
        raise RefusedError(f"what the script makes already exists: {', '.join(existing)} (moved already?)")
    unknown = sorted(name for name in found if name not in PLACES and name not in BASE)
    if unknown:
        raise RefusedError(
            "modules that PLACES does not place: "
            + ", ".join(f"{PACKAGE}/{name}{'.py' if found[name] == 'module' else '/'}" for name in unknown)
            + ": add each to PLACES (or BASE) in scripts/relayout.py, with its part"
        )
    notices = [f"notice: {name} is in PLACES but not in {PACKAGE}/: skipped" for name in PLACES if name not in found]
    for name in PLACES:
        if name in found and new_place(name)[1] in found and new_place(name)[1] != name:
            raise RefusedError(f"{name} would become {new_place(name)[1]}, which is already a module: rename one")
    return notices


def byte_to_char(line: str, column: int) -> int:
    """Returns the character offset of a UTF-8 byte offset in a line (ast gives byte offsets)."""
    return len(line.encode("utf-8")[:column].decode("utf-8", errors="replace"))


def bindings(tree: ast.AST) -> tuple[set[str], set[str]]:
    """Returns (names bound anywhere in the module other than by `from matfit import`, every name read or bound)."""
    bound, seen = set(), set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Name):
            seen.add(node.id)
            if not isinstance(node.ctx, ast.Load):
                bound.add(node.id)
        elif isinstance(node, ast.arg):
            bound.add(node.arg)
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef, ast.ExceptHandler)):
            bound.add(node.name or "")
        elif isinstance(node, (ast.Global, ast.Nonlocal)):
            bound.update(node.names)
        elif isinstance(node, (ast.MatchAs, ast.MatchStar)) and node.name:
            bound.add(node.name)
        elif isinstance(node, ast.MatchMapping) and node.rest:
            bound.add(node.rest)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            if isinstance(node, ast.ImportFrom) and node.module == PACKAGE and node.level == 0:
                continue
            for alias in node.names:
                bound.add(alias.asname or alias.name.split(".")[0])
    seen |= bound
    return bound, seen


def rewrite_imports(path: str, source: str, found: dict[str, str]) -> tuple[str, list[str]]:
    """Rewrites `from matfit import ...` statements of a Python file (and renames uses of renamed modules)."""
    tree = ast.parse(source, filename=path)
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level:
            relative = f"{path}:{node.lineno}: relative import"
            inside_package = path.startswith(f"{PACKAGE}/") and path.count("/") >= 2 and node.level == 1
            if not inside_package:
                raise RefusedError(f"{relative}: write it as an absolute import (`from matfit.x import y`) first")
    statements = [
        node
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom)
        and node.module == PACKAGE
        and node.level == 0
        and any(alias.name in PLACES and alias.name in found for alias in node.names)
    ]
    bound, seen = bindings(tree)
    renames, notes = {}, []
    for node in statements:
        for alias in node.names:
            if alias.name in PLACES and alias.name in found and alias.asname is None:
                new = new_place(alias.name)[1]
                if new != alias.name:
                    if alias.name in bound or new in seen:
                        notes.append(f"{path}: imports {new} as {alias.name} (the file binds one of the names)")
                    else:
                        renames[alias.name] = new
    lines = source.splitlines(keepends=True)
    offsets = [0]
    for line in lines:
        offsets.append(offsets[-1] + len(line))

    def offset(line: int, column: int) -> int:
        return offsets[line - 1] + byte_to_char(lines[line - 1], column)

    uses = {name: [] for name in renames}
    for node in ast.walk(tree):
        if isinstance(node, ast.Name) and node.id in renames:
            start = offset(node.lineno, node.col_offset)
            uses[node.id].append((start, start + len(node.id), renames[node.id]))
    for name, spans in uses.items():
        if any(source[start:end] != name for start, end, _ in spans):  # a position ast got wrong (an f-string)
            notes.append(f"{path}: imports {renames.pop(name)} as {name} (a use inside an f-string)")
    edits = [span for name in renames for span in uses[name]]
    for node in statements:
        start, end = offset(node.lineno, node.col_offset), offset(node.end_lineno, node.end_col_offset)
        line_start = source.rfind("\n", 0, start) + 1
        indent = source[line_start:start]
        separator = "\n" + indent if not indent.strip() else "; "
        staying, moving = [], {}
        for alias in node.names:
            if alias.name in PLACES and alias.name in found:
                part, new = new_place(alias.name)
                local = alias.asname or (alias.name if alias.name not in renames else new)
                moving.setdefault(part, []).append(new if local == new else f"{new} as {local}")
            else:
                staying.append(alias.name if alias.asname is None else f"{alias.name} as {alias.asname}")
        generated = [f"from {MARK} import {', '.join(staying)}"] if staying else []
        generated += [f"from {MARK}.{part} import {', '.join(names)}" for part, names in moving.items()]
        edits.append((start, end, separator.join(generated)))
    for start, end, text in sorted(edits, reverse=True):
        source = source[:start] + text + source[end:]
    return source, notes


def text_rules(found: dict[str, str], exported: dict[str, set[str]]):
    """Returns the function that rewrites dotted names, paths, string imports and prose in any text."""
    moved = sorted((name for name in PLACES if name in found), key=len, reverse=True)
    alternatives = "|".join(map(re.escape, moved))
    renamed = {name: new_place(name)[1] for name in moved if new_place(name)[1] != name}
    pattern = re.compile(
        rf"(?P<statement>from {PACKAGE} import (?P<names>\w+(?:[ \t]*,[ \t]*\w+)*)(?P<use>;[ \t]*(?P<used>\w+)\.)?)"
        rf"|(?P<path>{PACKAGE}/(?P<path_unit>{alternatives})(?P<path_end>\.py\b|/))"
        rf"|(?P<dotted>(?<![\w.]){PACKAGE}\.(?P<dotted_unit>{alternatives})\b)"
        + (
            rf"|(?P<file>(?<![\w/.-])(?P<file_unit>{'|'.join(map(re.escape, renamed))})\.py\b)"
            rf"|(?P<reference>(?<=`)(?P<reference_unit>{'|'.join(map(re.escape, renamed))})\.(?P<attribute>\w+))"
            if renamed
            else ""
        )
    )

    def replace(match: re.Match) -> str:
        if match["statement"]:
            names = [name.strip() for name in match["names"].split(",")]
            if not any(name in moved for name in names):
                return match[0]
            if names == [match["used"]] and names[0] in renamed:  # one line of code: `from matfit import x; x.y`
                part, new = new_place(names[0])
                return f"from {PACKAGE}.{part} import {new}; {new}."
            staying = [name for name in names if name not in moved]
            pieces = [f"from {PACKAGE} import {', '.join(staying)}"] if staying else []
            for name in names:
                if name in moved:
                    part, new = new_place(name)
                    pieces.append(f"from {PACKAGE}.{part} import {new}{'' if new == name else f' as {name}'}")
            return "; ".join(pieces) + (match["use"] or "")
        if match["path"]:
            part, new = new_place(match["path_unit"])
            return f"{PACKAGE}/{part}/{new}{match['path_end']}"
        if match["dotted"]:
            return new_dotted(match["dotted_unit"])
        if match["file"]:
            return f"{renamed[match['file_unit']]}.py"
        if match["attribute"] in exported.get(match["reference_unit"], ()):
            return f"{renamed[match['reference_unit']]}.{match['attribute']}"
        return match[0]

    vowels = [new for new in renamed.values() if new[0] in "aeiou"]
    article = re.compile(rf"\b([Aa]) (`(?:{'|'.join(vowels)})\.)") if vowels else None

    def rewrite(text: str) -> str:
        text = pattern.sub(replace, text)
        return article.sub(r"\1n \2", text) if article else text  # "a `render.X`" -> "an `engine.X`"

    return rewrite


FILE_USE = re.compile(r"((?:os\.path\.dirname\()+)os\.path\.abspath\(__file__\)(\)*)")


def fix_file_paths(path: str, unit: str, text: str, found: dict[str, str]) -> str:
    """Keeps a moved module's paths built from `__file__` pointing where they pointed; refuses unknown uses."""
    for module, old, new in SPECIAL_EDITS:
        if module == unit:
            if text.count(old) != 1:
                raise RefusedError(f"{path}: expected `{old}` once (SPECIAL_EDITS): update the table")
            text = text.replace(old, new)
    depth_inside = path.count("/") - 1  # 0: matfit/x.py, 1: matfit/unit/x.py
    out = []
    for number, line in enumerate(text.splitlines(keepends=True), 1):
        if "__file__" in line and not re.search(r"[\"']__file__[\"']\s*:", line):
            uses = list(FILE_USE.finditer(line))
            if not uses:
                raise RefusedError(f"{path}:{number}: a use of __file__ the script does not know: {line.strip()}")
            for use in reversed(uses):
                depth = use.group(1).count("dirname")
                if depth <= depth_inside:
                    continue  # a folder inside the moved package: it moves with it
                siblings = re.findall(r"[\"'](\w+)\.py[\"']", line)
                if depth == 1 and siblings:
                    if all(name in PLACES and new_place(name)[0] == new_place(unit)[0] for name in siblings):
                        continue  # a sibling that moves into the same part
                    raise RefusedError(f"{path}:{number}: {siblings} do not move to {new_place(unit)[0]}/ with {unit}")
                if depth == 1 and unit == "blender_scene":
                    continue  # its own folder, fixed by SPECIAL_EDITS
                line = line[: use.start()] + "os.path.dirname(" + use.group(0) + ")" + line[use.end() :]
        out.append(line)
    return "".join(out)


def module_names(path: str) -> set[str]:
    """Returns the names a module defines at its top level (for backticked references in prose)."""
    names = set()
    for node in ast.parse(Path(path).read_text(encoding="utf-8")).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names.update(target.id for target in targets if isinstance(target, ast.Name))
        elif isinstance(node, ast.ImportFrom):
            names.update(alias.asname or alias.name for alias in node.names)
    return names


def plan(tracked: list[str], found: dict[str, str]) -> tuple[dict[str, str], list[tuple[str, str]], list[str]]:
    """Returns (new contents by current path, moves as (old, new) paths, notes), touching nothing."""
    exported = {
        name: module_names(f"{PACKAGE}/{name}.py")
        for name in PLACES
        if found.get(name) == "module" and new_place(name)[1] != name
    }
    rules = text_rules(found, exported)
    contents, notes = {}, []
    for path in tracked:
        if not (path in REWRITTEN or path.split("/")[0] in REWRITTEN) or path == "scripts/relayout.py":
            continue
        if not (path.endswith(TEXT_SUFFIXES) or "/" not in path or path.startswith(".ci/")):
            continue
        if path.startswith(f"{PACKAGE}/data/"):
            continue
        with open(path, encoding="utf-8") as file:
            text = original = file.read()
        if path.endswith(".py"):
            text, file_notes = rewrite_imports(path, text, found)
            notes += file_notes
        text = rules(text).replace(MARK, PACKAGE)
        pieces = path.split("/")
        if pieces[0] == PACKAGE and len(pieces) >= 2 and pieces[1].removesuffix(".py") in PLACES:
            text = fix_file_paths(path, pieces[1].removesuffix(".py"), text, found)
        if text != original:
            contents[path] = text
    moves = []
    for name in sorted(PLACES):
        if name in found:
            part, new = new_place(name)
            suffix = ".py" if found[name] == "module" else ""
            moves.append((f"{PACKAGE}/{name}{suffix}", f"{PACKAGE}/{part}/{new}{suffix}"))
    return contents, moves, notes


def find_ruff(explicit: str | None) -> str | None:
    if explicit:
        return explicit
    beside = Path(sys.executable).parent / "ruff"
    return str(beside) if beside.exists() else shutil.which("ruff")


def apply(contents: dict[str, str], moves: list[tuple[str, str]], ruff: str | None) -> None:
    for part in PARTS:
        os.makedirs(os.path.join(PACKAGE, part))
        init = os.path.join(PACKAGE, part, "__init__.py")
        with open(init, "w", encoding="utf-8") as file:
            file.write(f'"""{wrap(DOCSTRINGS[part])}"""\n')
    for old, new in moves:
        run("git", "mv", old, new)
    renamed = dict(moves)
    for path, text in contents.items():
        target = renamed.get(path) or next(
            (new + path[len(old) :] for old, new in moves if path.startswith(old + "/")), path
        )
        with open(target, "w", encoding="utf-8") as file:
            file.write(text)
    with open(os.path.join("tests", "test_layout.py"), "w", encoding="utf-8") as file:
        file.write(LAYOUT_TEST)
    run("git", "add", *(os.path.join(PACKAGE, part, "__init__.py") for part in PARTS), "tests/test_layout.py")
    if ruff is None:
        print("notice: ruff not found: run `ruff check --fix --select I matfit tests scripts` and `ruff format`")
    else:
        folders = [folder for folder in (PACKAGE, "tests", "scripts") if os.path.isdir(folder)]
        subprocess.run([ruff, "check", "--fix", "--select", "I", "--quiet", *folders], check=False)
        subprocess.run([ruff, "format", "--quiet", *folders], check=False)
    run("git", "add", "-u")


def wrap(text: str, width: int = 116) -> str:
    """Returns a paragraph broken into lines of at most `width` characters (the docstring's quotes included)."""
    lines, line = [], ""
    for word in text.split():
        if line and len(line) + 1 + len(word) > width:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}" if line else word
    return "\n".join([*lines, line])


def table() -> str:
    """Returns the layout as a Markdown table: each part, what it may import, its modules (renamed ones marked)."""
    rows = ["| part | may import | modules |", "|---|---|---|"]
    modules = {"base": [f"`{name}`" for name in BASE if not name.startswith("__")] + ["`__main__` (may import app)"]}
    for name in PLACES:
        part, new = new_place(name)
        modules.setdefault(part, []).append(f"`{new}`" + ("" if new == name else f" (was `{name}.py`)"))
    for index, part in enumerate(("base", *PARTS)):
        below = ", ".join(("base", *PARTS)[: index + 1])
        rows.append(f"| `matfit/{'' if part == 'base' else part + '/'}` | {below} | {', '.join(modules[part])} |")
    return "\n".join(rows)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dry-run", action="store_true", help="print the plan and change nothing")
    parser.add_argument("--ruff", help="the ruff executable (default: beside this Python, else on PATH)")
    parser.add_argument("--table", action="store_true", help="print the layout as a Markdown table (for docs/)")
    arguments = parser.parse_args()
    if arguments.table:
        print(table())
        return 0
    try:
        if not os.path.isfile(os.path.join(PACKAGE, "__init__.py")):
            raise RefusedError("run it at the repository root (the folder holding matfit/)")
        tracked = run("git", "ls-files").splitlines()
        found = units(tracked)
        notes = check_tree(tracked, found)
        contents, moves, file_notes = plan(tracked, found)
    except RefusedError as refused:
        print(f"error: {refused}", file=sys.stderr)
        return 2
    for old, new in moves:
        print(f"move {old} -> {new}")
    for path in sorted(contents):
        print(f"rewrite {path}")
    for note in notes + sorted(set(file_notes)):
        print(note)
    if arguments.dry_run:
        return 0
    apply(contents, moves, find_ruff(arguments.ruff))
    print("done: review `git diff --cached -M --stat`, run the tests, then commit")
    return 0


if __name__ == "__main__":
    sys.exit(main())
