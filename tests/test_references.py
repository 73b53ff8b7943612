"""Every dotted ``daemodel.`` path and every source file named in the docs, the README and the
docstrings exists: a module, function or class that moves takes its references with it."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TEXTS = sorted(
    [
        ROOT / "README.md",
        *(ROOT / "docs").rglob("*.md"),
        *(ROOT / "daemodel").rglob("*.py"),
        *(ROOT / "backends").rglob("*.py"),
    ]
)
DOTTED = re.compile(r"\bdaemodel(?:\.[A-Za-z_][A-Za-z0-9_]*)+")
FILE = re.compile(r"\b(?:daemodel|backends|tests|benchmarks|examples|build_backend)/[A-Za-z0-9_/]*\.py\b")


def resolves(path: str) -> bool:
    """Whether ``path`` names a module, or an attribute (a class's too) of the longest module it starts with."""
    parts = path.split(".")
    for i in range(len(parts), 0, -1):
        try:
            target = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for k, attribute in enumerate(parts[i:], i + 1):
            if hasattr(target, attribute):
                target = getattr(target, attribute)
            else:  # an instance's attribute a class declares (a dataclass field without a default)
                return k == len(parts) and attribute in getattr(target, "__annotations__", {})
        return True
    return False


def references(pattern: re.Pattern) -> list[tuple[str, str]]:
    return sorted(
        {
            (str(text.relative_to(ROOT)), m.group(m.lastindex or 0))
            for text in TEXTS
            for m in pattern.finditer(text.read_text())
        }
    )


@pytest.mark.parametrize(("where", "path"), references(DOTTED))
def test_every_dotted_path_imports(where, path):
    assert resolves(path), f"{where} names {path}, which does not import"


@pytest.mark.parametrize(("where", "path"), references(FILE))
def test_every_named_source_file_exists(where, path):
    assert (ROOT / path).is_file(), f"{where} names {path}, which does not exist"


# A reST role's target with a leading dot (``:func:`.compiled.refresh_function```): Sphinx takes it as a
# suffix of some object's full name.
SUFFIX = re.compile(r":(?:mod|func|class|meth|data|attr|exc):`~?(\.[\w.]+)`")


def _modules() -> list[str]:
    names = []
    for folder, package in (("daemodel", "daemodel"), ("backends", "daemodel.backends")):
        for path in (ROOT / folder).rglob("*.py"):
            parts = [p for p in path.relative_to(ROOT / folder).with_suffix("").parts if p != "__init__"]
            names.append(".".join([package, *parts]))
    return names


@pytest.mark.parametrize(("where", "suffix"), references(SUFFIX))
def test_every_dotted_suffix_names_something(where, suffix):
    assert any(resolves(f"{module}{suffix}") for module in _modules()), f"{where} names {suffix}, which is nowhere"


def test_a_moved_name_is_caught():
    assert resolves("daemodel.compiling.zero_test.exact_value")
    assert not resolves("daemodel.compiling.structure.exact_value")
    assert not resolves("daemodel.solving.nowhere")
    assert resolves("daemodel.comparing.tables.Run.solve_time")  # (a dataclass field)
    assert not resolves("daemodel.comparing.tables.Run.nowhere")
