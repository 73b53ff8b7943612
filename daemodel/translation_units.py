"""One generated C source cut into translation units that a C compiler can build in parallel.

A first compile of radau's machine code is one compiler run over one source (casadi's code
generator's and :mod:`daemodel.backends.radau.kernel`'s), of which 80-90 % is gcc's optimisation
of the functions' bodies, one after the other.  Cut into units that are compiled at the same time
(``cc -c``, one process each) and linked into one library, the same code at the same ``-O`` level
takes the time of its largest unit, plus one link.  The cut changes no arithmetic: every function
keeps its body, the flags stay (no fused multiply-adds: the same bits), and only a call from one
unit into another can no longer be inlined.

What :func:`split` understands is the shape of that source: at file level only preprocessor
lines, comments, ``static const`` arrays (on one line or several, ending with ``;``) and function
definitions (the header at column 0, the body up to a ``}`` at column 0, or on the header's line).
Everything that is not a function goes, in its order, in front of every unit (the macros, types
and constant arrays all functions read); casadi's small helpers (``casadi_copy``, ``casadi_sq``,
...; non-static, named ``casadi_`` but not ``casadi_f<k>``) go there too, made ``static``, so that
each unit inlines its own copy; every other function is defined in exactly one unit and declared
in all of them, a ``static`` one made visible across the units but not outside the library
(``visibility("hidden")``).  Functions are dealt to the units in their order, in runs of about
equal size (a function and those it calls, which the generator writes just before it, mostly stay
together).  Anything else at file level (a variable that is not ``const``: each unit would hold
its own copy) makes :func:`split` decline, and the source is compiled whole.
"""

from __future__ import annotations

import re

# A function definition's first line: at column 0, words and "*" up to its name and "(" (then a "{" comes
# before any ";": a definition, not a declaration).
_HEADER = re.compile(r"(?:static\s+)?(?:CASADI_SYMBOL_EXPORT\s+)?[A-Za-z_][\w\s\*]*?\b(\w+)\s*\(")
# casadi's helpers, duplicated into every unit as static functions (its generated functions are casadi_f<k>).
_HELPER = re.compile(r"casadi_(?!f\d+$)\w+")
# What a static function becomes when the units share it: visible to the other units, not outside the library.
HIDDEN = '__attribute__((visibility("hidden")))'
# Units below this many characters of function bodies are not worth a compiler process (~40 ms to start,
# and the shared part parsed again): a source is cut into at most len(bodies) / UNIT_MIN_CHARS units.
UNIT_MIN_CHARS = 20_000


class _Function:
    """A function definition: its name, its lines, and whether it was ``static``."""

    def __init__(self, name: str, lines: list[str]):
        self.name, self.lines = name, lines
        self.static = lines[0].startswith("static ")

    @property
    def size(self) -> int:
        return sum(len(line) + 1 for line in self.lines)

    def prototype(self) -> str:
        """The declaration: the text up to the body's ``{``, then ``;`` (``static`` made hidden)."""
        text = "\n".join(self.lines)
        head = text[: text.index("{")].rstrip()
        return (HIDDEN + " " + head[len("static ") :] if self.static else head) + ";"

    def shared(self) -> list[str]:
        """The definition for one unit among several (``static`` made hidden)."""
        if not self.static:
            return self.lines
        return [HIDDEN + " " + self.lines[0][len("static ") :], *self.lines[1:]]

    def local(self) -> list[str]:
        """The definition as a static function of every unit (casadi's helpers)."""
        return self.lines if self.static else ["static " + self.lines[0], *self.lines[1:]]


def _parse(source: str) -> tuple[list, list[_Function]] | None:
    """The file-level items: the shared part (lines and helper functions, in order) and the other
    functions; None where an item is not of the shapes the module docstring lists."""
    lines = source.split("\n")
    shared, functions, i = [], [], 0
    while i < len(lines):
        line = lines[i]
        stripped = line.strip()
        if stripped.startswith("/*"):  # a comment, on this line or several
            while "*/" not in lines[i]:
                shared.append(lines[i])
                i += 1
                if i == len(lines):
                    return None
            shared.append(lines[i])
            i += 1
            continue
        if not stripped or stripped.startswith(("#", "//")):  # (blank, preprocessor, indented or not)
            shared.append(line)
            i += 1
            continue
        if line[0] in " \t":
            return None  # (indented code at file level: not a shape this module knows)
        if line.startswith("static const "):
            while not lines[i].rstrip().endswith(";"):
                shared.append(lines[i])
                i += 1
                if i == len(lines):
                    return None
            shared.append(lines[i])
            i += 1
            continue
        match = _HEADER.match(line)
        rest = "\n".join(lines[i : i + 3])
        if match is None or "{" not in rest or (";" in rest and rest.index(";") < rest.index("{")):
            return None  # (a variable, a declaration, or anything else at file level)
        start = i
        if not (line.rstrip().endswith("}") and "{" in line):
            while lines[i] != "}":
                i += 1
                if i == len(lines):
                    return None
        function = _Function(match[1], lines[start : i + 1])
        i += 1
        if _HELPER.fullmatch(function.name) and not function.static:
            shared.append(function)
        else:
            functions.append(function)
    return shared, functions


def split(source: str, units: int) -> list[str] | None:
    """``source`` cut into at most ``units`` translation units (fewer where the functions' bodies are
    small: :data:`UNIT_MIN_CHARS`), each a complete C source; None where one unit is all there is, or
    the source has a shape this module does not cut (see the module docstring): compile it whole."""
    parsed = _parse(source)
    if parsed is None:
        return None
    shared, functions = parsed
    total = sum(function.size for function in functions)
    units = min(units, total // UNIT_MIN_CHARS)
    if units < 2:
        return None
    front = []
    for item in shared:
        front += item.local() if isinstance(item, _Function) else [item]
    front += ["/* daemodel: the functions of every unit */", *(function.prototype() for function in functions)]
    groups, size = [[]], 0
    for function in functions:  # (runs of about total / units characters, in order)
        if size >= (len(groups)) * total / units and len(groups) < units:
            groups.append([])
        groups[-1].append(function)
        size += function.size
    out = []
    for index, group in enumerate(groups):
        body = [f"/* daemodel: translation unit {index + 1} of {len(groups)} */"]
        for function in group:
            body += function.shared()
        out.append("\n".join(front + body) + "\n")
    return out
