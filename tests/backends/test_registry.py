"""Methods found by name (backends/registry.py): built in, registered with ``dm.methods.register``, or
installed under the ``daemodel.methods`` entry-point group; every refusal named."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import ClassVar

import pytest
from daemodel.backends import get_backend
from daemodel.backends.base import AbstractBackend
from daemodel.backends.radau.backend import RadauBackend

import daemodel as dm
from daemodel import errors as E

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "plugin_method"
BUILT_IN = ("radau", "casadi-collocation", "casadi-idas", "reference", "pinn")


@pytest.fixture
def example(monkeypatch):
    """The example's module (examples/plugin_method/whole_span_pinn.py), importable as an installed one is."""
    monkeypatch.syspath_prepend(str(EXAMPLE))
    import whole_span_pinn

    return whole_span_pinn


@pytest.fixture
def registered(example):
    """``whole-span-pinn`` registered for one test, unregistered after it."""
    dm.methods.register("whole-span-pinn", example.WholeSpanPINN)
    yield example
    dm.methods.unregister("whole-span-pinn")


def install(root: Path, distribution: str, points: dict[str, str]) -> None:
    """A distribution's metadata as pip leaves it (``<name>-<version>.dist-info``) with ``points`` in the
    ``daemodel.methods`` group, under ``root`` (which the test puts on sys.path)."""
    info = root / f"{distribution.replace('-', '_')}-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {distribution}\nVersion: 1.0\n")
    lines = "".join(f"{name} = {value}\n" for name, value in points.items())
    (info / "entry_points.txt").write_text(f"[daemodel.methods]\n{lines}")


def test_the_built_in_methods_come_first_and_nothing_else_is_listed_unasked():
    assert dm.methods() == BUILT_IN
    assert isinstance(get_backend("radau"), RadauBackend)


def test_register_makes_a_method_of_solve_and_the_listing(registered):
    assert dm.methods() == (*BUILT_IN, "whole-span-pinn")
    assert isinstance(get_backend("whole-span-pinn"), registered.WholeSpanPINN)
    dm.methods.unregister("whole-span-pinn")
    assert dm.methods() == BUILT_IN
    with pytest.raises(E.UnknownMethodError, match="unknown method 'whole-span-pinn'; the methods are radau"):
        get_backend("whole-span-pinn")
    dm.methods.register("whole-span-pinn", registered.WholeSpanPINN)  # (the fixture unregisters it)


def test_replace_takes_a_built_in_name_and_unregister_gives_it_back(example):
    class Radau(example.WholeSpanPINN):
        name: ClassVar[str] = "radau"

    dm.methods.register("radau", Radau, replace=True)
    try:
        assert type(get_backend("radau")) is Radau
        assert dm.methods() == BUILT_IN
    finally:
        dm.methods.unregister("radau")
    assert type(get_backend("radau")) is RadauBackend


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("my method", r"method name 'my method' is not a plain name: a letter, then letters, digits and single '-'"),
        ("-lead", "method name '-lead' is not a plain name"),
        ("double--dash", "method name 'double--dash' is not a plain name"),
        ("x" * 65, r"method name 'x{64}\.\.\.' is not a plain name: .* at most 64 characters"),
        (3, "a method name must be a string; got int 3"),
    ],
)
def test_a_method_name_that_is_not_plain_is_refused(example, name, message):
    with pytest.raises(E.MethodNameError, match=message):
        dm.methods.register(name, example.WholeSpanPINN)
    assert issubclass(E.MethodNameError, E.InvalidNameError)


def test_a_taken_name_is_refused_without_replace(registered):
    class Radau(registered.WholeSpanPINN):
        name: ClassVar[str] = "radau"

    with pytest.raises(E.MethodNameError, match="method name 'radau' is taken: a built-in method; pass replace=True"):
        dm.methods.register("radau", Radau)
    with pytest.raises(E.MethodNameError, match=r"'whole-span-pinn' is taken: registered earlier \(WholeSpanPINN\)"):
        dm.methods.register("whole-span-pinn", registered.WholeSpanPINN)
    with pytest.raises(E.MethodNameError, match="replace must be True or False; got 1"):
        dm.methods.register("whole-span-pinn", registered.WholeSpanPINN, replace=1)


@dataclasses.dataclass(frozen=True, kw_only=True)
class _Options:
    t_eval: object = None


def _class(**attributes):
    """A subclass of the example's method with ``attributes`` changed (a broken contract to refuse)."""
    from whole_span_pinn import WholeSpanPINN

    return type("Broken", (WholeSpanPINN,), attributes)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: 42, "expected a subclass of daemodel.backends.base.AbstractBackend .*; got int 42"),
        (lambda: RadauBackend(), r"expected a subclass .*\(the class, not an instance\); got RadauBackend"),
        (lambda: dict, "expected a subclass of daemodel.backends.base.AbstractBackend .*; got dict"),
        (
            lambda: type("Abstract", (AbstractBackend,), {"name": "mine", "Options": _Options, "max_index": 1}),
            "class Abstract is abstract: define solve",
        ),
        (lambda: _class(name="other"), r"class Broken has name = 'other'; .* set name = 'mine' in the class"),
        (lambda: _class(name="mine", Options=dict), "class Broken's Options must be a .*dataclass of its options"),
        (lambda: _class(name="mine", max_index=4), "class Broken's max_index must be 1, 2 or 3 .*; got 4"),
        (lambda: _class(name="mine", max_index=True), "class Broken's max_index must be 1, 2 or 3 .*; got True"),
    ],
)
def test_a_class_that_breaks_the_contract_is_refused(example, make, message):
    with pytest.raises(E.MethodClassError, match=f"method 'mine': {message}"):
        dm.methods.register("mine", make())
    assert "mine" not in dm.methods()


def test_unregister_names_what_was_registered():
    with pytest.raises(
        E.UnknownMethodError, match=r"no method 'radau' was registered in this process \(registered: none"
    ):
        dm.methods.unregister("radau")
    with pytest.raises(E.UnknownMethodError, match=r"no method \['x'\] was registered in this process"):
        dm.methods.unregister(["x"])


def test_an_installed_method_is_found_by_its_entry_point(tmp_path, monkeypatch, example):
    install(tmp_path, "daemodel-whole-span-pinn", {"whole-span-pinn": "whole_span_pinn:WholeSpanPINN"})
    monkeypatch.syspath_prepend(str(tmp_path))
    assert dm.methods() == (*BUILT_IN, "whole-span-pinn")
    assert isinstance(get_backend("whole-span-pinn"), example.WholeSpanPINN)
    with pytest.raises(
        E.MethodNameError,
        match=r"'whole-span-pinn' is taken: installed by entry point 'whole-span-pinn' = "
        r"'whole_span_pinn:WholeSpanPINN' of distribution 'daemodel-whole-span-pinn 1.0' \(group daemodel.methods\)",
    ):
        dm.methods.register("whole-span-pinn", example.WholeSpanPINN)
    monkeypatch.undo()  # (sys.path as before: the distribution is gone, and so is its method)
    assert dm.methods() == BUILT_IN


def test_a_broken_entry_point_is_named_and_the_others_work(tmp_path, monkeypatch, example):
    install(tmp_path, "daemodel-whole-span-pinn", {"whole-span-pinn": "whole_span_pinn:WholeSpanPINN"})
    install(
        tmp_path,
        "broken-methods",
        {
            "missing": "no_such_module_for_daemodel:Method",
            "not-a-backend": "json:dumps",
            "twice": "whole_span_pinn:WholeSpanPINN",
            "bad.name": "whole_span_pinn:WholeSpanPINN",
            "radau": "whole_span_pinn:WholeSpanPINN",
        },
    )
    install(tmp_path, "other-methods", {"twice": "whole_span_pinn:WholeSpanPINN"})
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.warns(E.MethodPluginWarning) as caught:
        names = dm.methods()
    messages = sorted(str(w.message) for w in caught)
    assert messages == [
        "entry point 'bad.name' = 'whole_span_pinn:WholeSpanPINN' of distribution 'broken-methods 1.0' (group "
        "daemodel.methods) is ignored: 'bad.name' is not a plain method name (a letter, then letters, digits and "
        "single '-' or '_')",
        "entry point 'radau' = 'whole_span_pinn:WholeSpanPINN' of distribution 'broken-methods 1.0' (group "
        "daemodel.methods) is ignored: 'radau' is a built-in method, which is used; the distribution should choose "
        "another name",
    ]
    assert names == (*BUILT_IN, "missing", "not-a-backend", "twice", "whole-span-pinn")
    with pytest.raises(
        E.MethodPluginError,
        match=r"method 'missing' cannot be loaded from entry point 'missing' = 'no_such_module_for_daemodel:Method' "
        r"of distribution 'broken-methods 1.0' \(group daemodel.methods\): ModuleNotFoundError: No module named "
        "'no_such_module_for_daemodel'",
    ):
        get_backend("missing")
    with pytest.raises(
        E.MethodPluginError,
        match=r"method 'not-a-backend' from entry point 'not-a-backend' = 'json:dumps' of distribution 'broken-methods "
        r"1.0' \(group daemodel.methods\) breaks the backend contract: method 'not-a-backend': expected a subclass",
    ):
        get_backend("not-a-backend")
    with pytest.raises(
        E.MethodPluginError,
        match=r"method 'twice' is declared by 2 entry points, entry point 'twice' = .* of distribution '(broken|other)"
        r"-methods 1.0' and entry point 'twice' = .* of distribution '(broken|other)-methods 1.0' .*: uninstall one",
    ):
        get_backend("twice")
    # (the others work: the built-ins and the installed method beside the broken ones)
    assert isinstance(get_backend("whole-span-pinn"), example.WholeSpanPINN)
    assert isinstance(get_backend("radau"), RadauBackend)
    assert "no_such_module_for_daemodel" not in sys.modules


def every_method(root: Path, monkeypatch, who: str) -> tuple[list, dict]:
    """The warnings and the backends of a call given no methods (``who``), with the distributions
    installed under ``root`` on sys.path."""
    from daemodel.backends import backends_for

    monkeypatch.syspath_prepend(str(root))
    with pytest.warns(E.MethodPluginWarning) as caught:
        backends = backends_for(None, who)
    return [str(w.message) for w in caught], backends


def test_a_broken_installed_method_is_left_out_of_a_run_over_every_method(tmp_path, monkeypatch, example):
    """compare() and bench() with no methods given run every method: one installed method that does not
    load left them unable to start (MethodPluginError); now it is left out with a warning naming it,
    and the others run. Named explicitly, it still raises."""
    install(tmp_path, "daemodel-whole-span-pinn", {"whole-span-pinn": "whole_span_pinn:WholeSpanPINN"})
    install(tmp_path, "broken-methods", {"missing": "no_such_module_for_daemodel:Method"})
    messages, backends = every_method(tmp_path, monkeypatch, "bench")
    assert messages == [
        "bench leaves out method 'missing' cannot be loaded from entry point 'missing' = "
        "'no_such_module_for_daemodel:Method' of distribution 'broken-methods 1.0' (group daemodel.methods): "
        "ModuleNotFoundError: No module named 'no_such_module_for_daemodel'"
    ]
    assert list(backends) == ["radau", "casadi-collocation", "casadi-idas", "pinn", "whole-span-pinn"]
    assert isinstance(backends["whole-span-pinn"], example.WholeSpanPINN)
    with pytest.raises(E.MethodPluginError, match="method 'missing' cannot be loaded"):
        dm.bench(["paper"], ["missing"], tmp_path / "out", progress=False)


def test_an_installed_method_whose_class_cannot_be_constructed_is_left_out_too(tmp_path, monkeypatch, example):
    """A class that imports and keeps the contract but whose constructor raises (a method that needs a
    GPU, a licence) stopped compare() and bench() without methods with its own exception; it is a
    MethodPluginError naming the entry point, left out with a warning there, raised where named."""
    (tmp_path / "needs_gpu.py").write_text(
        "from whole_span_pinn import WholeSpanPINN\n\n\nclass NeedsGPU(WholeSpanPINN):\n"
        "    name = 'needs-gpu'\n\n    def __init__(self):\n        raise RuntimeError('no GPU here')\n"
    )
    install(tmp_path, "needs-gpu", {"needs-gpu": "needs_gpu:NeedsGPU"})
    messages, backends = every_method(tmp_path, monkeypatch, "compare()")
    assert messages == [
        "compare() leaves out method 'needs-gpu' from entry point 'needs-gpu' = 'needs_gpu:NeedsGPU' of "
        "distribution 'needs-gpu 1.0' (group daemodel.methods) cannot be constructed: RuntimeError: no GPU here"
    ]
    assert list(backends) == ["radau", "casadi-collocation", "casadi-idas", "pinn"]
    with pytest.raises(E.MethodPluginError, match=r"method 'needs-gpu' from entry point .* RuntimeError: no GPU here$"):
        get_backend("needs-gpu")


def test_a_method_named_twice_is_a_named_error_not_merged_silently(tmp_path):
    """methods=["radau", "radau"]: compare() and bench() kept it twice before backends_for, then merged
    it into one without a word; it is a DuplicateMethodError naming the method and the call."""
    from daemodel.backends import backends_for

    with pytest.raises(E.DuplicateMethodError, match=r"^bench is given method 'radau' twice in methods; name each"):
        backends_for(["radau", "casadi-idas", "radau"], "bench")
    with pytest.raises(E.UnknownMethodError):  # (an unknown name is still that, before any duplicate)
        backends_for(["radau", "nope", "radau"], "bench")
    assert list(backends_for(["casadi-idas", "radau"], "bench")) == ["casadi-idas", "radau"]
    m = dm.Model("decay")
    (x,) = m.states("x")
    (w,) = m.algebraics("w")
    m.ode(x, -w)
    m.constraint(w - x, name="tie")
    m.initial(x=1.0, w=1.0)
    with pytest.raises(E.DuplicateMethodError, match=r"^compare\(\) is given method 'radau' twice"):
        dm.compare(m, (0.0, 1.0), ["radau", "radau"])
    with pytest.raises(E.DuplicateMethodError, match=r"^bench is given method 'pinn' twice"):
        dm.bench(["paper"], ["pinn", "radau", "pinn"], tmp_path / "out", progress=False)
