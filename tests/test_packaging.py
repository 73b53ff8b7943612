"""Install layout and import hygiene."""

import subprocess
import sys


def python(code, cwd):
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=cwd).stdout


def test_backends_install_as_daemodel_backends(tmp_path):
    out = python("import importlib.util, daemodel.backends; print(importlib.util.find_spec('backends'))", tmp_path)
    assert out.strip() == "None"  # no top-level 'backends' package outside the repository


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
        "CompiledDAE",
        "Comparison",
        "EnsembleFiles",
        "Model",
        "PINNConfig",
        "RadauIIA",
        "Solution",
        "Surrogate",
        "compare",
        "ensemble",
        "errors",
        "methods",
        "radau_iia",
        "solve",
    }


def test_console_script_runs(tmp_path):
    # the installed entry point: pyproject's [project.scripts] daemodel = "daemodel.cli:main"
    out = subprocess.run(
        [sys.executable, "-c", "from daemodel.cli import main; main(['compare', '--help'])"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert out.returncode == 0 and "build_model()" in out.stdout
