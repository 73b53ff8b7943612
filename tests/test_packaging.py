"""Install layout and import hygiene."""

import subprocess
import sys


def python(code, cwd):
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=cwd).stdout


def test_backends_install_as_daemodel_backends(tmp_path):
    out = python("import importlib.util, daemodel.backends; print(importlib.util.find_spec('backends'))", tmp_path)
    assert out.strip() == "None"  # no top-level 'backends' package outside the repository


def test_every_package_folder_is_installed():
    """Each folder with an __init__.py under daemodel/ and backends/ is in pyproject's packages, where
    package-dir says (an editable install finds a missing one; a wheel leaves it out)."""
    import tomllib
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    setuptools = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]
    declared = {name: root / folder for name, folder in setuptools["package-dir"].items()}
    assert set(setuptools["packages"]) == set(declared)
    found = set()
    for top, name in (("daemodel", "daemodel"), ("backends", "daemodel.backends")):
        for init in (root / top).rglob("__init__.py"):
            parts = init.parent.relative_to(root / top).parts
            found.add(".".join((name, *parts)))
    assert found == set(declared)
    assert all((folder / "__init__.py").exists() for folder in declared.values())


def test_import_has_no_side_effects(tmp_path):
    out = python(
        "import sys, io, contextlib\n"
        "buf = io.StringIO()\n"
        "with contextlib.redirect_stdout(buf):\n"
        "    import daemodel\n"
        "print(repr(buf.getvalue()), 'torch' in sys.modules)",
        tmp_path,
    )
    assert out.strip() == "'' False"  # prints nothing; torch loads only when code is generated


def test_public_api():
    import daemodel as dm

    assert set(dm.__all__) == {
        "BenchResult",
        "CompiledDAE",
        "Comparison",
        "EnsembleFiles",
        "Fit",
        "Model",
        "PINNConfig",
        "RadauIIA",
        "Solution",
        "Stencil",
        "Surrogate",
        "bench",
        "compare",
        "ensemble",
        "errors",
        "fit",
        "methods",
        "radau_iia",
        "solve",
        "stencil",
    }


def test_console_script_runs(tmp_path):
    # the installed entry point: pyproject's [project.scripts] daemodel = "daemodel.comparing.cli:main"
    out = subprocess.run(
        [sys.executable, "-c", "from daemodel.comparing.cli import main; main(['compare', '--help'])"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert out.returncode == 0 and "build_model()" in out.stdout
