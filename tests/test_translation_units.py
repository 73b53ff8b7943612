"""One generated C source cut into translation units (daemodel/translation_units.py), compiled at
once through the disk cache (daemodel/cache.py): the same functions, the same values, one library."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest
from daemodel.backends.radau.compiled import COMPILER_FLAGS, find_compiler

from daemodel import cache, translation_units
from daemodel.errors import CompileError

pytestmark = pytest.mark.skipif(find_compiler() is None, reason="no C compiler on PATH")

# In front of casadi's code, as radau's kernel (backends/radau/kernel.py) stands in front of it: a
# comment over several lines, arrays, static functions that casadi's code calls through a code-only
# function, and an exported one.
KERNEL = """/* a kernel in front of casadi's code:
   a comment on two lines */
#include <math.h>
#define N_TWICE 3
static const int twice_index[3] = {0,1,2};
static const double twice_factor[1] = {0x1.0p+1};

static void dm_twice(const double* x, double* out) {
  int q;
  for (q = 0; q < N_TWICE; q++) out[twice_index[q]] = twice_factor[0] * x[q];
}

int dm_kernel_size(void) { return N_TWICE; }
"""


def casadi_source(count: int = 6) -> tuple[str, list[str]]:
    """casadi's C for ``count`` functions of x (3), each calling the one before (never inlined: one
    definition each) and one calling the kernel's ``dm_twice``; with :data:`KERNEL` in front."""
    import casadi

    x = casadi.SX.sym("x", 3)
    twice = casadi.Function.jit(
        "twice", "dm_twice(x, out); return 0;", ["x"], ["out"], [casadi.Sparsity.dense(3)],
        [casadi.Sparsity.dense(3)], {"jit": False, "buffered": False},
    )  # fmt: skip
    functions = [casadi.Function("g0", [x], [casadi.sin(x) * x + casadi.exp(-x * x)])]
    for k in range(1, count):
        y = casadi.MX.sym("y", 3)
        previous = functions[-1].call([y], False, True)[0]
        functions.append(casadi.Function(f"g{k}", [y], [previous * casadi.cos(y) + twice(y) + k]))
    generator = casadi.CodeGenerator("daemodel_jit")
    for function in functions:
        generator.add(function)
    return KERNEL + generator.dump(), [function.name() for function in functions]


def build(units: int = 1, compiler: str | None = None) -> cache.Build:
    return cache.Build(compiler or find_compiler(), COMPILER_FLAGS, "compiling", "fix it", ("-lm",), units=units)


def values(functions: dict, names) -> list[np.ndarray]:
    x = np.array([0.5, -1.25, 2.0])
    return [np.asarray(functions[name](x)).ravel() for name in names]


def test_a_source_cut_into_units_is_the_same_library(monkeypatch, tmp_path):
    monkeypatch.setattr(translation_units, "UNIT_MIN_CHARS", 500)
    source, names = casadi_source()
    units = translation_units.split(source, 3)
    assert units is not None and len(units) == 3
    # each function is defined in one unit and declared in all (static ones made hidden, not exported)
    for name in ("casadi_f0", "dm_twice"):
        header = f"{translation_units.HIDDEN} "
        defined = [
            unit
            for unit in units
            if any(line.startswith(header) and f" {name}(" in line and line.endswith("{") for line in unit.split("\n"))
        ]
        assert len(defined) == 1, name
    assert all(unit.count(f"{translation_units.HIDDEN} void dm_twice(const double* x, double* out);") == 1
               for unit in units)  # fmt: skip
    # casadi's helpers: static in every unit (inlined where called)
    assert all("static void casadi_copy(" in unit or "casadi_copy(" not in unit for unit in units)
    whole_folder, split_folder = tmp_path / "whole", tmp_path / "split"
    whole_folder.mkdir()
    split_folder.mkdir()
    whole = cache.load(cache.compile_library(source, whole_folder, build(1)), names)
    monkeypatch.setattr(cache, "workers", lambda: 3)
    library = cache.compile_library(source, split_folder, build(3))
    assert sorted(path.name for path in split_folder.glob("unit*.o")) == ["unit0.o", "unit1.o", "unit2.o"]
    cut = cache.load(library, names)
    for a, b in zip(values(whole, names), values(cut, names), strict=True):
        assert np.array_equal(a, b)
    # the same exported names, nothing of the units' sharing among them
    exported = [
        {line.split()[-1] for line in subprocess.run(["nm", "-D", "--defined-only", str(path)], capture_output=True,
                                                     text=True, check=True).stdout.splitlines()}
        for path in (whole_folder / "library.so", library)
    ]  # fmt: skip
    assert set(names) <= exported[1] and "dm_kernel_size" in exported[1]
    assert not any(name.startswith(("daemodel_jit_f", "dm_twice")) for name in exported[1])


def test_a_small_source_is_not_cut():
    source, _ = casadi_source(2)
    assert translation_units.split(source, 8) is None  # (below UNIT_MIN_CHARS a unit: one is all there is)
    assert translation_units.split(source, 1) is None


@pytest.mark.parametrize(
    "extra",
    [
        "static double counter = 0.0;\n",  # (each unit would hold its own copy)
        "int calls;\n",
        "  int indented = 1;\n",
        "static const double unfinished[2] = {1.0,\n",
        "static void unfinished(void) {\n  return;\n",
    ],
)
def test_a_shape_it_does_not_know_is_compiled_whole(monkeypatch, extra):
    monkeypatch.setattr(translation_units, "UNIT_MIN_CHARS", 500)
    source, _ = casadi_source()
    assert translation_units.split(source, 3) is not None
    assert translation_units.split(extra + source if "unfinished" not in extra else source + extra, 3) is None


def test_the_cache_key_counts_the_units_this_machine_runs(monkeypatch):
    source, _ = casadi_source()
    monkeypatch.setattr(cache, "workers", lambda: 1)
    one = cache.entry_key(source, build(1))
    assert cache.entry_key(source, build(4)) == one  # (one CPU: one unit, the key of a whole compile)
    monkeypatch.setattr(cache, "workers", lambda: 2)
    assert cache.entry_key(source, build(1)) == one
    two = cache.entry_key(source, build(4))
    assert two != one and cache.entry_key(source, build(2)) == two
    monkeypatch.setattr(cache, "workers", lambda: 8)
    assert cache.entry_key(source, build(4)) not in (one, two)


def test_units_through_the_cache_then_a_hit(monkeypatch, tmp_path):
    monkeypatch.setenv(cache.CACHE_VARIABLE, str(tmp_path / "cache"))
    monkeypatch.setattr(translation_units, "UNIT_MIN_CHARS", 500)
    monkeypatch.setattr(cache, "workers", lambda: 2)
    runs = []
    original = cache.run_compiler
    monkeypatch.setattr(
        cache, "run_compiler", lambda commands, *args: (runs.append(commands), original(commands, *args))
    )
    source, names = casadi_source()
    first = cache.cached_library(source, names, build(4))
    assert first.outcome == "miss" and [len(commands) for commands in runs] == [2, 1]  # two units at once, a link
    assert runs[0][0][-4:] == ["-c", "unit0.c", "-o", "unit0.o"] and runs[1][0][-3:] == ["-o", "library.so", "-lm"]
    second = cache.cached_library(source, names, build(4))
    assert second.outcome == "hit" and len(runs) == 2
    for a, b in zip(values(first.functions, names), values(second.functions, names), strict=True):
        assert np.array_equal(a, b)


def test_a_failing_unit_names_the_compiler(monkeypatch, tmp_path):
    monkeypatch.setattr(translation_units, "UNIT_MIN_CHARS", 500)
    monkeypatch.setattr(cache, "workers", lambda: 2)
    source, _ = casadi_source()
    broken = source.replace(
        "int dm_kernel_size(void) { return N_TWICE; }", "int dm_kernel_size(void) { return N_TWICE }"
    )
    with pytest.raises(CompileError, match=r"compiling with .* failed: .*expected.*; fix it"):
        cache.compile_library(broken, tmp_path, build(2))
    with pytest.raises(CompileError, match=r"compiling with /bin/false failed: no message; fix it"):
        cache.compile_library(source, tmp_path, build(2, "/bin/false"))
