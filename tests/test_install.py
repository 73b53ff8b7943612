"""The editable install resolves to the real package from any folder, the clone's parent included.

A clone is a folder named ``daemodel`` without an ``__init__.py``; seen from its parent, Python's
path finder takes it for a namespace package unless the install's finder is asked first
(build_backend/daemodel_build.py).  The test installs a copy of the repository, editable, into a bare
virtual environment (the packages daemodel needs come from this interpreter's site-packages through
a path file) and runs a script from the copy's parent.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "build_backend"))
import daemodel_build  # noqa: E402

SCRIPT = """import daemodel as dm
import daemodel.backends
print(dm.__file__)
print(daemodel.backends.__file__)
print(dm.Model.__name__)
"""


def _copy_of_the_repository(target: Path) -> None:
    tracked = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    for name in tracked.splitlines():
        if (ROOT / name).is_file() and name.split("/")[0] in ("daemodel", "backends", "build_backend"):
            (target / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, target / name)
    for name in ("pyproject.toml", "README.md", "MANIFEST.in"):
        shutil.copy2(ROOT / name, target / name)


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git to list the repository's files")
def test_an_editable_install_is_found_from_the_clones_parent_folder(tmp_path):
    clone = tmp_path / "daemodel"
    clone.mkdir()
    _copy_of_the_repository(clone)
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    site = Path(
        subprocess.run(
            [python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    )
    # numpy, sympy, torch, setuptools, ... from this interpreter (a path line: its .pth files, this
    # checkout's own editable install among them, are not run)
    (site / "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    pip = [sys.executable, "-m", "pip", "--python", str(python), "install", "--quiet", "--no-deps"]
    install = subprocess.run(
        [*pip, "--no-build-isolation", "--no-index", "-e", str(clone)],
        capture_output=True,
        text=True,
    )
    assert install.returncode == 0, install.stdout + install.stderr
    (tmp_path / "script.py").write_text(SCRIPT)
    for folder in (tmp_path, clone, tmp_path / "venv"):
        run = subprocess.run([python, str(tmp_path / "script.py")], cwd=folder, capture_output=True, text=True)
        assert run.returncode == 0, f"from {folder}: {run.stderr}"
        package, backends, model = run.stdout.split()
        assert Path(package) == clone / "daemodel" / "__init__.py", folder
        assert Path(backends) == clone / "backends" / "__init__.py", folder
        assert model == "Model"


def _wheel(path: Path, pth: str, record_extra: str = "") -> Path:
    with zipfile.ZipFile(path, "w") as wheel:
        wheel.writestr("__editable__.daemodel-0.1.0.pth", pth)
        wheel.writestr("__editable___daemodel_0_1_0_finder.py", "MAPPING = {}\n")
        wheel.writestr(
            "daemodel-0.1.0.dist-info/RECORD",
            "__editable__.daemodel-0.1.0.pth,sha256=old,10\n__editable___daemodel_0_1_0_finder.py,sha256=x,13\n"
            + record_extra
            + "daemodel-0.1.0.dist-info/RECORD,,\n",
        )
    return path


def test_the_editable_wheels_finder_goes_first_and_its_record_is_rewritten(tmp_path):
    import base64
    import hashlib

    line = "import __editable___daemodel_0_1_0_finder; __editable___daemodel_0_1_0_finder.install()"
    wheel = _wheel(tmp_path / "w.whl", line)
    assert daemodel_build.finder_first(wheel)
    with zipfile.ZipFile(wheel) as rewritten:
        pth = rewritten.read("__editable__.daemodel-0.1.0.pth")
        record = rewritten.read("daemodel-0.1.0.dist-info/RECORD").decode().splitlines()
        assert rewritten.read("__editable___daemodel_0_1_0_finder.py") == b"MAPPING = {}\n"
    assert pth.decode() == (
        f"{line}; import sys; sys.meta_path.insert(0, sys.meta_path.pop(sys.meta_path.index("
        "__editable___daemodel_0_1_0_finder._EditableFinder)))\n"
    )
    digest = base64.urlsafe_b64encode(hashlib.sha256(pth).digest()).rstrip(b"=").decode()
    assert record[0] == f"__editable__.daemodel-0.1.0.pth,sha256={digest},{len(pth)}"
    assert record[1:] == ["__editable___daemodel_0_1_0_finder.py,sha256=x,13", "daemodel-0.1.0.dist-info/RECORD,,"]


def test_a_wheel_without_setuptools_finder_line_is_left_as_it_is(tmp_path):
    wheel = _wheel(tmp_path / "w.whl", "/some/path\n")
    before = wheel.read_bytes()
    assert not daemodel_build.finder_first(wheel)
    assert wheel.read_bytes() == before


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git to list the repository's files")
def test_a_wheel_built_from_the_sdist_holds_the_package_and_daemodel_backends_only(tmp_path):
    """The sdist carries the build backend (pyproject's backend-path), so pip can build a wheel from
    it; that wheel holds every module of daemodel/ and backends/ (as daemodel.backends), and neither
    build_backend nor a top-level backends package."""
    source = tmp_path / "source"
    source.mkdir()
    _copy_of_the_repository(source)
    build = (
        "import sys; sys.path.insert(0, 'build_backend'); import daemodel_build; "
        f"print(daemodel_build.build_sdist({str(tmp_path)!r}))"
    )
    sdist = subprocess.run([sys.executable, "-c", build], cwd=source, capture_output=True, text=True)
    assert sdist.returncode == 0, sdist.stderr
    name = sdist.stdout.split()[-1]
    wheel = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation", "--no-index",
         "-w", str(tmp_path / "wheels"), str(tmp_path / name)],
        capture_output=True,
        text=True,
    )  # fmt: skip
    assert wheel.returncode == 0, wheel.stdout + wheel.stderr
    (built,) = (tmp_path / "wheels").glob("daemodel-*.whl")
    with zipfile.ZipFile(built) as archive:
        modules = {name for name in archive.namelist() if name.endswith(".py")}
    expected = {str(p.relative_to(ROOT)) for p in (ROOT / "daemodel").rglob("*.py")}
    expected |= {"daemodel/" + str(p.relative_to(ROOT)) for p in (ROOT / "backends").rglob("*.py")}
    assert modules == expected
