"""daemodel's build backend: setuptools', with one change to editable installs.

``backends/`` at the top of the repository installs as ``daemodel.backends``, so setuptools makes an
editable install with an import hook (a finder appended to ``sys.meta_path``) rather than a path
entry.  Python asks its path finder first, and that finder takes a folder named ``daemodel`` without
an ``__init__.py`` in the current script's folder, such as the clone itself seen from its parent, for
a namespace package: ``import daemodel`` then gives an empty module (``module 'daemodel' has no
attribute 'Model'``).  Here the editable wheel's ``.pth`` line also moves setuptools' finder to the
front of ``sys.meta_path``; it answers only for ``daemodel`` and what is under it, so nothing else
resolves differently.  Wheels and sdists are setuptools' own.
"""

from __future__ import annotations

import base64
import hashlib
import re
import zipfile
from pathlib import Path

from setuptools import build_meta
from setuptools.build_meta import *  # noqa: F403  (every hook not defined below is setuptools')

# The line setuptools writes into the editable wheel's .pth file.
SETUPTOOLS_LINE = re.compile(r"^import (__editable___\w+_finder); \1\.install\(\)\s*$")


def build_editable(wheel_directory, config_settings=None, metadata_directory=None):
    name = build_meta.build_editable(wheel_directory, config_settings, metadata_directory)
    finder_first(Path(wheel_directory) / name)
    return name


def finder_first(wheel: Path) -> bool:
    """Rewrite the editable wheel's ``.pth`` so that its finder goes first in ``sys.meta_path``
    (its RECORD updated); False, the wheel unchanged, where it holds no such line."""
    with zipfile.ZipFile(wheel) as source:
        items = [(info, source.read(info)) for info in source.infolist()]
    changed = {}
    for info, data in items:
        match = SETUPTOOLS_LINE.match(data.decode()) if info.filename.endswith(".pth") else None
        if match:
            module = match.group(1)
            changed[info.filename] = (
                f"import {module}; {module}.install(); import sys; "
                f"sys.meta_path.insert(0, sys.meta_path.pop(sys.meta_path.index({module}._EditableFinder)))\n"
            ).encode()
    if not changed:
        return False
    out = []
    for info, data in items:
        data = changed.get(info.filename, data)
        if info.filename.endswith(".dist-info/RECORD"):
            data = _record(data.decode(), changed).encode()
        out.append((info, data))
    temporary = wheel.with_suffix(".tmp")
    with zipfile.ZipFile(temporary, "w", zipfile.ZIP_DEFLATED) as target:
        for info, data in out:
            target.writestr(info, data)
    temporary.replace(wheel)
    return True


def _record(text: str, changed: dict) -> str:
    """RECORD with the hash and size of each changed file."""
    lines = []
    for line in text.splitlines():
        path = line.split(",")[0]
        if path in changed:
            digest = base64.urlsafe_b64encode(hashlib.sha256(changed[path]).digest()).rstrip(b"=").decode()
            line = f"{path},sha256={digest},{len(changed[path])}"
        lines.append(line)
    return "\n".join(lines) + "\n"
