"""README's Python snippets run as written.

Each block that imports daemodel starts a script; a block that does not continues the script
before it (README's walk-through builds ``m`` once and uses it below).  Every script runs in its
own process, in a scratch directory, and must exit 0 without a traceback.
"""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parent.parent / "README.md"
# A script's time limit: the PINN snippet trains a fast-mode PINN, a shortened paper run and a surrogate.
SCRIPT_LIMIT_S = 600


def readme_scripts() -> list[str]:
    """README's ```python blocks, joined into scripts (see the module docstring)."""
    scripts = []
    for block in re.findall(r"```python\n(.*?)```", README.read_text(), re.S):
        if "import daemodel as dm" in block or not scripts:
            scripts.append(block)
        else:
            scripts[-1] += "\n" + block
    return scripts


def test_readme_has_the_snippets_this_test_runs():
    scripts = readme_scripts()
    assert len(scripts) == 5  # the walk-through (model, solve), ensembles, compare, the PINN, parallel PINN training
    assert all("import daemodel as dm" in script for script in scripts)


@pytest.mark.parametrize(
    "index",
    [0, 1, 2, pytest.param(3, marks=pytest.mark.slow), 4],  # the PINN snippet trains for a minute or more
    ids=["walk-through", "ensemble", "compare", "pinn", "parallel-pinn"],
)
def test_readme_snippet_runs(index, tmp_path):
    source = readme_scripts()[index]
    if 'engine="ray"' in source and "#" not in source.split('engine="ray"')[0].splitlines()[-1]:
        pytest.importorskip("ray")  # the snippet needs the ray extra (CI installs it)
    script = tmp_path / "snippet.py"
    script.write_text(source)
    env = {**os.environ, "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1"}
    done = subprocess.run(
        [sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=SCRIPT_LIMIT_S
    )
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr[-3000:]
