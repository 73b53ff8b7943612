"""The layers of daemodel import downward only, and no module imports another's private name.

Every module's imports are read with ``ast`` (imports inside functions too): a module may import
its own layer or one below it, never one above; ``from m import _name`` across modules is refused
(what two modules share is a public function of one of them, or a small module of its own).  The
layers are drawn in docs/README.md#layout.
"""

from __future__ import annotations

import ast
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# From the bottom up: (layer, the first component of each module name under daemodel. in it).
# daemodel/__init__.py, the front door, sits above them all.
LAYERS = (
    ("core", ("errors", "files", "tableau", "reals", "collocation", "messages", "executors")),
    ("declaring", ("declaring",)),
    ("compiling", ("compiling",)),
    ("the Solution", ("solution", "solution_files", "stats", "dense", "sensitivities", "instants", "plotting")),
    ("backends", ("backends",)),
    ("solving", ("solving",)),
    ("problems", ("problems",)),
    ("comparing and fitting", ("comparing", "fitting")),
    ("testing", ("testing",)),
)
FRONT = len(LAYERS)
# Where the source trees install: backends/ at the top of the repository is daemodel.backends.
TREES = (("daemodel", "daemodel"), ("backends", "daemodel.backends"))


def modules(root: Path) -> dict[str, Path]:
    """Module name -> file, over both source trees under ``root``."""
    out = {}
    for folder, package in TREES:
        for path in sorted((root / folder).rglob("*.py")):
            parts = [p for p in path.relative_to(root / folder).with_suffix("").parts if p != "__init__"]
            out[".".join([package, *parts])] = path
    return out


def layer(module: str) -> int | None:
    """The layer's index of a daemodel module name; None where no layer holds it."""
    if module == "daemodel":
        return FRONT
    first = module.removeprefix("daemodel.").split(".")[0]
    return next((i for i, (_, names) in enumerate(LAYERS) if first in names), None)


def imports(name: str, path: Path):
    """``(line, imported module, imported name or "")`` of every import in the file, relative ones
    resolved."""
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name, ""
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                module = ".".join([*base, *([node.module] if node.module else [])])
            else:
                module = node.module or ""
            for alias in node.names:
                yield node.lineno, module, alias.name


def violations(root: Path) -> list[str]:
    """Every upward import, unplaced module and cross-module private import under ``root``."""
    found = []
    table = modules(root)
    for name, path in table.items():
        own = layer(name)
        where = path.relative_to(root)
        if own is None:
            found.append(f"{where}: module {name} is in no layer (add it to LAYERS and to docs/README.md#layout)")
            continue
        for line, module, imported in imports(name, path):
            if not (module == "daemodel" or module.startswith("daemodel.")) or name == "daemodel":
                continue
            target = f"{module}.{imported}" if f"{module}.{imported}" in table else module
            other = layer(target)
            if other is None:
                found.append(f"{where}:{line}: imports {target}, which is in no layer")
            elif other > own:
                found.append(
                    f"{where}:{line}: {name} ({LAYERS[own][0]}) imports {target} ({_layer_name(other)}), a layer above"
                )
            if imported.startswith("_") and not imported.startswith("__") and module != name:
                found.append(f"{where}:{line}: {name} imports the private name {imported} of {module}")
    return list(dict.fromkeys(found))  # (one line for an import of several names)


def _layer_name(index: int) -> str:
    return "the package's front" if index == FRONT else LAYERS[index][0]


def test_every_module_imports_its_own_layer_or_below_and_no_private_name():
    found = violations(ROOT)
    assert not found, "\n".join(found)


def test_every_layer_is_drawn_in_the_development_docs():
    layout = (ROOT / "docs" / "README.md").read_text()
    for title, _ in LAYERS:
        assert title in layout, f"docs/README.md#layout does not name the layer {title!r}"


@pytest.fixture
def tree(tmp_path):
    for folder, _ in TREES:
        shutil.copytree(ROOT / folder, tmp_path / folder)
    return tmp_path


def _plant(path: Path, line: str, inside_a_function: bool = False) -> None:
    text = path.read_text()
    if inside_a_function:
        line = f"\n\ndef _planted():\n    {line}\n"
    path.write_text(text + "\n" + line + "\n")


@pytest.mark.parametrize(
    ("file", "line", "inside", "expected"),
    [
        (
            "daemodel/declaring/model.py",
            "from daemodel.solving.solver import solve",
            False,
            "daemodel/declaring/model.py:{n}: daemodel.declaring.model (declaring) imports daemodel.solving.solver "
            "(solving), a layer above",
        ),
        (
            "daemodel/solution.py",
            "from daemodel.comparing.compare import compare",
            True,
            "daemodel/solution.py:{n}: daemodel.solution (the Solution) imports daemodel.comparing.compare "
            "(comparing and fitting), a layer above",
        ),
        (
            "backends/radau/step.py",
            "from ...solving import solver",
            True,
            "backends/radau/step.py:{n}: daemodel.backends.radau.step (backends) imports daemodel.solving.solver "
            "(solving), a layer above",
        ),
        (
            "daemodel/compiling/init.py",
            "import daemodel.solving.events",
            False,
            "daemodel/compiling/init.py:{n}: daemodel.compiling.init (compiling) imports daemodel.solving.events "
            "(solving), a layer above",
        ),
        (
            "daemodel/solving/events.py",
            "from daemodel.compiling.structure import _planted_helper",
            False,
            "daemodel/solving/events.py:{n}: daemodel.solving.events imports the private name _planted_helper of "
            "daemodel.compiling.structure",
        ),
        (
            "daemodel/errors.py",
            "import daemodel",
            True,
            "daemodel/errors.py:{n}: daemodel.errors (core) imports daemodel (the package's front), a layer above",
        ),
    ],
)
def test_a_planted_import_is_named(tree, file, line, inside, expected):
    assert violations(tree) == []
    _plant(tree / file, line, inside)
    n = next(i for i, text in enumerate((tree / file).read_text().splitlines(), 1) if text.strip() == line)
    assert violations(tree) == [expected.format(n=n)]


def test_a_module_in_no_layer_is_named(tree):
    (tree / "daemodel" / "gadgets.py").write_text("X = 1\n")
    assert violations(tree) == [
        "daemodel/gadgets.py: module daemodel.gadgets is in no layer (add it to LAYERS and to docs/README.md#layout)"
    ]


def circles(root: Path) -> list[list[str]]:
    """The import circles among the modules under ``root`` (strongly connected sets of two or more
    modules, or a module importing itself), each in name order; imports inside functions count."""
    table = modules(root)
    arrows: dict[str, set[str]] = {name: set() for name in table}
    for name, path in table.items():
        for _, module, imported in imports(name, path):
            target = f"{module}.{imported}" if f"{module}.{imported}" in table else module
            if target in table and name != "daemodel":
                arrows[name].add(target)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []

    def visit(node: str) -> None:  # Tarjan's strongly connected components
        index[node] = low[node] = len(index)
        stack.append(node)
        for other in sorted(arrows[node]):
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                component.append(member)
                if member == node:
                    break
            if len(component) > 1 or node in arrows[node]:
                found.append(sorted(component))

    for node in sorted(table):
        if node not in index:
            visit(node)
    return found


def test_no_module_imports_another_that_imports_it_back():
    assert circles(ROOT) == []


def test_a_planted_circle_is_named(tree):
    _plant(tree / "daemodel" / "stats.py", "from daemodel.solution import Solution", inside_a_function=True)
    assert circles(tree) == [["daemodel.solution", "daemodel.stats"]]
