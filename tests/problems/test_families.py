"""The families of the ``families`` suite: their sizes, their references (scipy on the index-reduced
ODE, written out as literals: recomputed here for the smallest members), a daemodel solve that agrees
with them, and the scaling benchmark that imports them."""

import importlib.util
import math
import sys
from pathlib import Path

import pytest

import daemodel as dm
from daemodel.comparing.suites import scd
from daemodel.errors import InvalidValueError
from daemodel.problems import FAMILIES
from daemodel.problems.families import SIZES, pendulum_chain, reaction_diffusion, scd_components

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


def _script(name):
    spec = importlib.util.spec_from_file_location(f"_fam_{name}", BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_each_family_has_three_sizes_named_by_family_and_size():
    assert list(FAMILIES) == [
        "pendulum_chain-4", "pendulum_chain-8", "pendulum_chain-16",
        "reaction_diffusion-25", "reaction_diffusion-50", "reaction_diffusion-100",
    ]  # fmt: skip
    for member in FAMILIES.values():
        assert member.name == f"{member.family}-{member.size}" and member.t_span == (0.0, 1.0)
        assert member.scd_names == scd_components(member.family, member.size) == tuple(member.reference)
        assert all(math.isfinite(v) and v != 0.0 for v in member.reference.values())
    assert SIZES == {"pendulum_chain": (4, 8, 16), "reaction_diffusion": (25, 50, 100)}


def test_the_smallest_members_have_the_unknowns_and_index_of_their_family():
    chain = FAMILIES["pendulum_chain-4"].model().compile()
    assert (len(chain.states), len(chain.algebraics)) == (16, 4)
    grid = FAMILIES["reaction_diffusion-25"].model().compile()
    assert (len(grid.states), len(grid.algebraics), grid.index) == (25, 25, 1)


@pytest.mark.parametrize("name", ["pendulum_chain-4", "reaction_diffusion-25"])
def test_the_literal_references_are_what_the_scipy_script_computes(name):
    script = _script("family_references")
    family, size = name.rsplit("-", 1)
    end = (script.chain_end if family == "pendulum_chain" else script.grid_end)(int(size), "Radau")
    assert {k: end[k] for k in FAMILIES[name].reference} == pytest.approx(FAMILIES[name].reference, rel=1e-10)


def test_a_tight_daemodel_solve_agrees_with_the_independent_reference():
    member = FAMILIES["pendulum_chain-4"]
    solution = dm.solve(member.model(), member.t_span, method="casadi-idas", rtol=1e-10, atol=1e-10)
    end = {n: float(solution[n][-1]) for n in member.reference}
    assert scd(end, member.reference)[0] > 7.5


def test_a_size_that_is_not_a_positive_integer_is_refused():
    with pytest.raises(InvalidValueError, match="pendulum_chain needs an integer N >= 1 links; got 0"):
        pendulum_chain(0)
    with pytest.raises(InvalidValueError, match=r"reaction_diffusion needs an integer K >= 1 grid points; got 2.0"):
        reaction_diffusion(2.0)


def test_the_scaling_benchmark_builds_the_same_models():
    sys.path.insert(0, str(BENCHMARKS))
    try:
        scaling_models = _script("scaling_models")
    finally:
        sys.path.remove(str(BENCHMARKS))
    assert scaling_models.FAMILIES["pendulum_chain"] is pendulum_chain
    assert scaling_models.FAMILIES["reaction_diffusion"] is reaction_diffusion
