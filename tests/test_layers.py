"""The layers of daemodel import downward only, and no module imports another's private name.

Every module's imports are read with ``ast`` (imports inside functions too): a module may import
its own layer or one below it, never one above; ``from m import _name`` across modules is refused
(what two modules share is a public function of one of them, or a small module of its own).  The
layers are drawn in docs/README.md#layout.
"""

from __future__ import annotations

import ast
import functools
import re
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# From the bottom up: (layer, the first component of each module name under daemodel. in it).
# daemodel/__init__.py, the front door, sits above them all.
LAYERS = (
    (
        "core",
        ("errors", "files", "cache", "translation_units", "tableau", "reals", "collocation", "messages", "executors"),
    ),
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


@functools.cache
def _parsed(text: str) -> ast.Module:
    """The syntax tree of a module's text, parsed once a run: the planted-import tests read a copy of
    the whole tree a test and change one file (every file parsed and walked again took ~9 s a test
    beside another test worker)."""
    return ast.parse(text)


def imports(name: str, path: Path) -> tuple[tuple[int, str, str], ...]:
    """``(line, imported module, imported name or "")`` of every import in the file, relative ones
    resolved; a literal string given to ``importlib.import_module`` or ``__import__`` and a
    ``"module:attribute"`` string naming a daemodel module (a registry's entry) count as imports."""
    return _imports(name, path.name == "__init__.py", path.read_text())


@functools.cache
def _imports(name: str, package_file: bool, text: str) -> tuple[tuple[int, str, str], ...]:
    return tuple(_walk_imports(name, package_file, _parsed(text)))


def _walk_imports(name: str, package_file: bool, tree: ast.Module):
    package = name.split(".") if package_file else name.split(".")[:-1]
    for node in ast.walk(tree):
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
        elif isinstance(node, ast.Call) and _called(node.func) in DYNAMIC and node.args:
            first = node.args[0]
            if isinstance(first, ast.Constant) and isinstance(first.value, str):
                yield node.lineno, first.value, ""
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and ENTRY.fullmatch(node.value):
            module, attribute = node.value.split(":")
            yield node.lineno, module, attribute


# Calls that import the module their literal string names, and a registry's "module:attribute".
DYNAMIC = ("import_module", "__import__")
ENTRY = re.compile(r"daemodel(\.\w+)*:\w+")


def _called(func: ast.expr) -> str:
    return func.id if isinstance(func, ast.Name) else func.attr if isinstance(func, ast.Attribute) else ""


def private_attributes(name: str, path: Path, table: dict[str, Path]) -> tuple[tuple[int, str, str], ...]:
    """``(line, module, name)`` of every private attribute read through a name bound to another
    daemodel module (``import daemodel.a.b as m; m._x``, ``from daemodel.a import b; b._x``,
    ``daemodel.a.b._x``)."""
    return _private_attributes(name, path.name == "__init__.py", path.read_text(), frozenset(table))


@functools.cache
def _private_attributes(name: str, package_file: bool, text: str, table: frozenset[str]):
    return tuple(_walk_private_attributes(name, package_file, text, table))


def _walk_private_attributes(name: str, package_file: bool, text: str, table: frozenset[str]):
    tree = _parsed(text)
    bound = {}
    for _, module, imported in _imports(name, package_file, text):
        if imported and f"{module}.{imported}" in table:
            bound[imported] = f"{module}.{imported}"
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.asname:
                    bound[alias.asname] = alias.name
                else:
                    bound[alias.name.split(".")[0]] = alias.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom):
            for alias in node.names:
                if alias.asname and alias.name in bound:
                    bound[alias.asname] = bound.pop(alias.name)
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
            dotted = _dotted(node.value)
            if dotted is None or dotted.split(".")[0] not in bound:
                continue
            head, _, rest = dotted.partition(".")
            module = ".".join(filter(None, [bound[head], rest]))
            if module in table and module != name:
                yield node.lineno, module, node.attr


def _dotted(node: ast.expr) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        inner = _dotted(node.value)
        return None if inner is None else f"{inner}.{node.attr}"
    return None


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
        for line, module, attribute in private_attributes(name, path, table):
            found.append(f"{where}:{line}: {name} reads the private name {attribute} of {module}")
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


def _layout() -> str:
    text = (ROOT / "docs" / "README.md").read_text()
    return text[text.index("## Layout") :]


def test_the_drawing_holds_what_layers_holds_and_each_exists():
    drawing = _layout().split("```text\n", 1)[1].split("```", 1)[0]
    rows = {}
    for row in drawing.splitlines():
        title = next((t for t, _ in LAYERS if row.startswith(t + " ")), None)
        if title is not None:
            rows[title] = set(re.findall(r"\b(\w+)(?:\.py\b|/)", row[len(title) :]))
    for title, names in LAYERS:
        assert rows.get(title) == set(names), (
            f"docs/README.md#layout draws {title} as {rows.get(title)}, LAYERS {names}"
        )
        for name in names:
            folder = ROOT / ("backends" if name == "backends" else f"daemodel/{name}")
            assert folder.is_dir() or folder.with_suffix(".py").is_file(), f"LAYERS names {name}, which does not exist"


def test_every_module_is_named_in_the_layout_and_every_file_it_names_exists():
    layout = _layout()
    for name, path in modules(ROOT).items():
        if path.name != "__init__.py":
            assert re.search(rf"(?<!\w){re.escape(path.name)}", layout), f"docs/README.md#layout does not name {name}"
    files = {
        p.name
        for folder in ("daemodel", "backends", "benchmarks", "tests", "build_backend")
        for p in (ROOT / folder).rglob("*.py")
    }
    for named in set(re.findall(r"\b\w+\.py\b", layout)):
        assert named in files, f"docs/README.md#layout names {named}, which does not exist"


@pytest.fixture
def tree(tmp_path):
    for folder, _ in TREES:
        shutil.copytree(ROOT / folder, tmp_path / folder)
    return tmp_path


def _plant(path: Path, line: str, inside: bool | str = False) -> None:
    """Append ``line`` to the file: at the top level, inside a function (``inside=True``) or under
    ``if TYPE_CHECKING:`` (``inside="TYPE_CHECKING"``)."""
    text = path.read_text()
    if inside == "TYPE_CHECKING":
        line = f"\n\nfrom typing import TYPE_CHECKING\n\nif TYPE_CHECKING:\n    {line}\n"
    elif inside:
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
        (
            "daemodel/compiling/structure.py",
            "import daemodel.solving.solver as s",
            True,
            "daemodel/compiling/structure.py:{n}: daemodel.compiling.structure (compiling) imports "
            "daemodel.solving.solver (solving), a layer above",
        ),
        (
            "daemodel/declaring/parse.py",
            "from daemodel import solving",
            False,
            "daemodel/declaring/parse.py:{n}: daemodel.declaring.parse (declaring) imports daemodel.solving "
            "(solving), a layer above",
        ),
        (
            "daemodel/compiling/init.py",
            "from .. import solving",
            True,
            "daemodel/compiling/init.py:{n}: daemodel.compiling.init (compiling) imports daemodel.solving "
            "(solving), a layer above",
        ),
        (
            "daemodel/compiling/init.py",
            "from ..solving import solver",
            False,
            "daemodel/compiling/init.py:{n}: daemodel.compiling.init (compiling) imports daemodel.solving.solver "
            "(solving), a layer above",
        ),
        (
            "daemodel/solution.py",
            "from daemodel.solving.solver import solve",
            "TYPE_CHECKING",
            "daemodel/solution.py:{n}: daemodel.solution (the Solution) imports daemodel.solving.solver "
            "(solving), a layer above",
        ),
        (
            "backends/__init__.py",
            'importlib.import_module("daemodel.solving.solver")',
            True,
            "backends/__init__.py:{n}: daemodel.backends (backends) imports daemodel.solving.solver "
            "(solving), a layer above",
        ),
        (
            "daemodel/dense.py",
            '__import__("daemodel.comparing.compare")',
            True,
            "daemodel/dense.py:{n}: daemodel.dense (the Solution) imports daemodel.comparing.compare "
            "(comparing and fitting), a layer above",
        ),
        (
            "backends/__init__.py",
            'REGISTRY["planted"] = "daemodel.solving.solver:solve"',
            False,
            "backends/__init__.py:{n}: daemodel.backends (backends) imports daemodel.solving.solver "
            "(solving), a layer above",
        ),
        (
            "daemodel/solving/events.py",
            "from daemodel.compiling import structure as planted; planted._planted_helper()",
            True,
            "daemodel/solving/events.py:{n}: daemodel.solving.events reads the private name _planted_helper of "
            "daemodel.compiling.structure",
        ),
        (
            "daemodel/solving/pieces.py",
            "import daemodel.compiling.structure; daemodel.compiling.structure._planted_helper()",
            True,
            "daemodel/solving/pieces.py:{n}: daemodel.solving.pieces reads the private name _planted_helper of "
            "daemodel.compiling.structure",
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
    _plant(tree / "daemodel" / "stats.py", "from daemodel.solution import Solution", inside=True)
    assert circles(tree) == [["daemodel.solution", "daemodel.stats"]]
