"""The one place where daemodel writes and reads files.

* **Checked before the work.**  A typo in a directory should cost a second, not a training run or
  a whole comparison: every user-named file or directory is checked here before the work that
  fills it (:func:`writable_file`, :func:`writable_directory`).
* **Atomic.**  Every file is written to a temporary file in the same directory (an unpredictable
  name, created exclusively, so a planted link is never followed), flushed, fsynced and renamed
  over the target (:func:`atomic_write`).  A write that fails or is interrupted (a full disk,
  kill -9) leaves the previous file as it was and no file that loads as complete.
* **Contained.**  A name that becomes part of a path (a model's name, a field read from a file, a
  chunk name in a manifest) is one plain file name (:func:`file_name`); what is read is opened
  without following links (:func:`open_inside`), so nothing is read or written outside the
  directory the user named.
* **Locked.**  A directory that a long run fills is held by a :class:`DirectoryLock` (an
  advisory ``flock``, released by the kernel when its process ends, so kill -9 leaves no stale
  lock on a local disk); a second writer is refused with the holder's process and host.
* **Sizes before allocation.**  A loader learns the sizes a file declares and compares them with
  the file's real size before it reads (:func:`stored_members`, :func:`read_json`).
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import re
import socket
import stat
import tempfile
import time
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from daemodel.errors import FileWriteError, InvalidOptionError, ResourceLimitError
from daemodel.messages import quoted

# A name daemodel puts into a path: letters, digits, '_', '-' and '.', not starting with '.'
# (no hidden files, no '.' or '..'), no separator of any platform.
FILE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.\-]{0,199}")
# The longest JSON file a loader reads, and the deepest nesting it accepts: a comparison or an
# ensemble manifest is flat (a manifest of 10^6 failed samples is about 200 MB).
JSON_BYTES = 1 << 30
JSON_DEPTH = 32
# The share of the memory this process may use that one result read or built may take, unless the
# environment variable DAEMODEL_MEMORY_LIMIT gives a size ("64G", "512M", bytes).
MEMORY_FRACTION = 0.5
MEMORY_LIMIT_VARIABLE = "DAEMODEL_MEMORY_LIMIT"
# The largest order of a dense matrix that the dense pieces (the reference's H_z, sensitivities'
# stage systems, the PINN inverse's H_z, the states' projection) allocate and factor: 5,000 x 5,000
# is 0.19 GiB and ~10^11 operations to factor (a minute on one core); beyond it they refuse.
DENSE_MAX_ORDER = 5_000
_UNITS = {"": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}
# Where the kernel states the memory of this process's control group: cgroup v2 (the file of the
# group named in /proc/self/cgroup, else of the root a container sees), cgroup v1.
CGROUP_TABLE = Path("/proc/self/cgroup")
CGROUP_ROOT = Path("/sys/fs/cgroup")
CGROUP_V1_LIMIT = Path("/sys/fs/cgroup/memory/memory.limit_in_bytes")
# A cgroup v1 "limit" at or above this is the kernel's way of saying none (PAGE_COUNTER_MAX pages).
CGROUP_V1_UNLIMITED = 1 << 60
# The cgroup's limit, once read, is read again where one of the files it came from changes (their inode,
# size or times: a file a test writes) and at the latest this many seconds later (the kernel's cgroup files
# need not change their times when a limit is written).
CGROUP_RECHECK = 1.0
_cgroup_kept: dict = {}  # (CGROUP_TABLE, CGROUP_ROOT, CGROUP_V1_LIMIT) -> (when read, files, signature, limit)


def _read_bytes(path: Path) -> int | None:
    """The whole number in the small file ``path``, or None (missing, unreadable, "max")."""
    try:
        text = path.read_text().strip()
    except (OSError, UnicodeDecodeError):
        return None
    return int(text) if text.isdigit() else None


def _cgroup_memory() -> int | None:
    """Bytes this process's control group may use, or None where no limit is set or visible: read once
    and kept while the files it came from keep their :func:`_signature` and for at most
    :data:`CGROUP_RECHECK` seconds (read on every solve, it was 7 % of the wheelset's: ~5,000 solves)."""
    key = (CGROUP_TABLE, CGROUP_ROOT, CGROUP_V1_LIMIT)
    kept = _cgroup_kept.get(key)
    now = time.monotonic()
    if kept is not None and now - kept[0] < CGROUP_RECHECK and _signature(kept[1]) == kept[2]:
        return kept[3]
    paths, limit = _read_cgroup_memory()
    _cgroup_kept.clear()
    _cgroup_kept[key] = (now, paths, _signature(paths), limit)
    return limit


def _signature(paths) -> tuple:
    """What tells that one of the files ``paths`` changed: each one's inode, size and times (None where
    there is none)."""
    signature = []
    for path in paths:
        try:
            found = os.stat(path)
        except OSError:
            signature.append(None)
            continue
        signature.append((found.st_ino, found.st_size, found.st_mtime_ns, found.st_ctime_ns))
    return tuple(signature)


def _read_cgroup_memory() -> tuple[tuple, int | None]:
    """``(the files read, :func:`_cgroup_memory`'s value)``, read from them now."""
    found = []
    try:
        lines = CGROUP_TABLE.read_text().splitlines()
    except (OSError, UnicodeDecodeError):
        lines = []
    paths = [CGROUP_TABLE]
    v1 = [CGROUP_V1_LIMIT]
    for line in lines:  # "0::/user.slice/..." names the v2 group, "4:memory:/docker/..." the v1 one
        number, _, rest = line.partition(":")
        controllers, _, group = rest.partition(":")
        group = group.strip().lstrip("/")
        if number == "0" and not controllers and group:
            paths.append(CGROUP_ROOT / group / "memory.max")
            found.append(_read_bytes(paths[-1]))
        elif "memory" in controllers.split(",") and group:
            v1.insert(0, CGROUP_V1_LIMIT.parent / group / CGROUP_V1_LIMIT.name)
    paths.append(CGROUP_ROOT / "memory.max")
    found.append(_read_bytes(paths[-1]))
    for path in v1:
        paths.append(path)
        value = _read_bytes(path)
        found.append(value if value is not None and value < CGROUP_V1_UNLIMITED else None)
    limits = [value for value in found if value]
    return tuple(paths), (min(limits) if limits else None)


def _address_space_left() -> int | None:
    """Bytes of address space this process may still map under its ``RLIMIT_AS``, or None without one."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
        if soft == resource.RLIM_INFINITY or soft < 0:
            return None
        used = int(Path("/proc/self/statm").read_text().split()[0]) * resource.getpagesize()
    except (ImportError, OSError, ValueError, IndexError):
        return None
    return max(soft - used, 0)


def memory_available() -> dict[str, int]:
    """What bounds the memory this process may use, by name (bytes): the machine's physical memory
    (8 GiB where the system does not say), its control group's limit (cgroup v2 ``memory.max`` or
    v1 ``memory.limit_in_bytes``) and the address space its ``RLIMIT_AS`` leaves, where set."""
    try:
        physical = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        physical = 8 << 30
    bounds = {
        "physical memory": physical,
        "cgroup memory limit": _cgroup_memory(),
        "address space left under RLIMIT_AS": _address_space_left(),
    }
    return {name: value for name, value in bounds.items() if value is not None}


def memory_limit() -> int:
    """Bytes one solve, batch, ensemble chunk or loaded result may take: ``DAEMODEL_MEMORY_LIMIT``
    when set (``"64G"``, ``"512M"``, a number of bytes), else :data:`MEMORY_FRACTION` of the least of
    :func:`memory_available` (the machine's RAM, the cgroup's limit, the address space left under
    ``RLIMIT_AS``): the one place daemodel decides how much memory it may take."""
    text = os.environ.get(MEMORY_LIMIT_VARIABLE, "").strip()
    if text:
        match = re.fullmatch(r"(\d+(?:\.\d+)?)\s*([KMGT]?)(?:i?B)?", text, flags=re.IGNORECASE)
        if match is None or float(match[1]) <= 0:
            raise InvalidOptionError(
                f"{MEMORY_LIMIT_VARIABLE} = {text!r} is not a memory size; give one such as '64G', '512M' or bytes"
            )
        return int(float(match[1]) * _UNITS[match[2].upper()])
    return int(MEMORY_FRACTION * min(memory_available().values()))


def _limit_source() -> str:
    """What :func:`memory_limit` is now, in words."""
    if os.environ.get(MEMORY_LIMIT_VARIABLE, "").strip():
        return f"now {MEMORY_LIMIT_VARIABLE}"
    bounds = memory_available()
    least = min(bounds, key=bounds.get)
    return f"now {MEMORY_FRACTION:g} of the {least} ({_size(bounds[least])})"


def _size(size: int) -> str:
    """``size`` bytes in the largest binary unit that keeps a digit before the point."""
    unit = max((u for u in _UNITS if _UNITS[u] <= max(size, 1)), key=_UNITS.get)
    return f"{size / _UNITS[unit]:.3g} {unit}iB" if unit else f"{size} bytes"


def check_memory(what: str, parts: dict) -> None:
    """A :class:`ResourceLimitError` when the ``parts`` (name: bytes) of ``what`` add up to more
    than :func:`memory_limit`, before anything is allocated; the message gives each part."""
    limit, total = memory_limit(), sum(parts.values())
    if total > limit:
        itemised = ", ".join(f"{name} {size / 2**30:.3g} GiB" for name, size in parts.items())
        raise ResourceLimitError(
            f"{what} would need {total / 2**30:.3g} GiB ({itemised}), more than the {limit / 2**30:.3g} GiB allowed "
            f"(set {MEMORY_LIMIT_VARIABLE}, e.g. '64G', to change it; {_limit_source()}): solve fewer samples at a "
            "time (dm.ensemble with a smaller chunk, write_to= to keep them on disk) or ask for fewer output times"
        )


def check_dense(what: str, order: int, fix: str, limit: int | None = None) -> None:
    """A :class:`ResourceLimitError` when ``what`` would allocate and factor a dense ``order x order``
    matrix above ``limit`` (default :data:`DENSE_MAX_ORDER`), before anything is allocated; the message
    names the size, the limit and ``fix``."""
    limit = DENSE_MAX_ORDER if limit is None else limit
    if order > limit:
        raise ResourceLimitError(
            f"{what} works on dense {order} x {order} matrices ({_size(8 * order * order)} each, order^3 "
            f"operations to factor), above its limit of {limit} x {limit}: {fix}"
        )


def readable_path(path, argument: str, error: type, what: str = "file") -> Path:
    """``path`` (``~`` expanded) for a loader, else ``error`` naming ``argument`` and what it takes:
    ``Path(3)`` or ``Path(None)`` would raise a bare TypeError that names neither."""
    if not isinstance(path, str | os.PathLike):
        raise error(
            f"{argument} must be a {what} path (str or pathlib.Path); got {quoted(path, 40)} ({type(path).__name__})"
        )
    return Path(path).expanduser()


def writable_file(path, argument: str) -> Path:
    """``path`` (``~`` expanded) if a file can be written there, else an :class:`InvalidOptionError`
    naming ``argument``, the path and the fix."""
    if not isinstance(path, str | os.PathLike):
        raise InvalidOptionError(f"{argument} must be a file path (str or Path); got {type(path).__name__}")
    path = Path(path).expanduser()
    if path.is_dir():
        raise InvalidOptionError(f"{argument} = '{path}' is a directory; give a file name in it")
    if not path.parent.is_dir():
        raise InvalidOptionError(
            f"{argument} = '{path}': the directory '{path.parent}' does not exist; create it first or write elsewhere"
        )
    if not os.access(path.parent, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise InvalidOptionError(f"{argument} = '{path}' is not writable; write elsewhere")
    return path


def writable_directory(path, argument: str) -> Path:
    """``path`` (``~`` expanded), created if missing, with a probe file created exclusively under an
    unpredictable name and removed; else an :class:`InvalidOptionError` naming ``argument``, the
    path and the reason."""
    if not isinstance(path, str | os.PathLike):
        raise InvalidOptionError(f"{argument} must be a directory path (str or Path); got {type(path).__name__}")
    path = Path(path).expanduser()
    if path.exists() and not path.is_dir():
        raise InvalidOptionError(f"{argument} {path} is an existing file, not a directory; give a directory")
    try:
        path.mkdir(parents=True, exist_ok=True)
        handle, probe = tempfile.mkstemp(dir=path, prefix=".daemodel-write-check-")
        os.close(handle)
        os.unlink(probe)
    except OSError as error:
        reason = error.strerror or str(error)
        where = f" ({error.filename})" if error.filename and str(error.filename) != str(path) else ""
        raise InvalidOptionError(
            f"{argument} {path} cannot be created or written: {reason}{where}; give a writable directory"
        ) from None
    return path


def file_name(name, field: str, error: type = InvalidOptionError) -> str:
    """``name`` if it is one plain file name (letters, digits, ``_``, ``-``, ``.``; not hidden, no
    separator, at most 200 characters), else ``error`` naming ``field`` and the name."""
    if not isinstance(name, str) or FILE_NAME.fullmatch(name) is None:
        raise error(
            f"{field} = {name!r} cannot name a file: a file name of letters, digits, '_', '-' and '.' is needed "
            "(no path separator, no leading '.', at most 200 characters)"
        )
    return name


@functools.cache
def _new_file_mode() -> int:
    """The mode a new file gets under this process's umask (read once, when first needed)."""
    umask = os.umask(0o022)
    os.umask(umask)
    return 0o666 & ~umask


def atomic_write(path: Path, write: Callable, *, text: bool = False, mode: int | None = None) -> Path:
    """Write ``path`` through ``write(handle)`` atomically: a temporary file beside it (created
    exclusively, unpredictable name), flushed and fsynced, then renamed over ``path`` (a link at
    ``path`` is replaced, never followed), and the directory fsynced.  ``mode``: the new file's
    permission bits (default: the file's it replaces, else the umask's).

    On any failure, an interrupt included, the temporary file is removed and ``path`` keeps its
    previous contents; an operating-system failure (a full disk, a file-size limit, a read-only
    file system) is a :class:`FileWriteError` naming the file and the reason.
    """
    path = Path(path)
    directory = path.parent
    try:
        if mode is None:  # (never a link's target's)
            mode = (os.lstat(path).st_mode & 0o777) if is_plain_file(path) else _new_file_mode()
        handle, temporary = tempfile.mkstemp(dir=directory, prefix=f".{path.name[:100]}.", suffix=".partial")
    except OSError as error:
        raise FileWriteError(f"{path} could not be written: {error.strerror or error}") from None
    try:
        os.fchmod(handle, mode)
        with os.fdopen(handle, "w" if text else "wb", **({"encoding": "utf-8", "newline": ""} if text else {})) as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(temporary, path)
    except BaseException as error:  # an interrupt too: no partial file is left behind
        with contextlib.suppress(OSError):
            os.unlink(temporary)
        if isinstance(error, OSError):
            raise FileWriteError(
                f"{path} could not be written ({error.strerror or error}); its previous contents, if any, are intact"
            ) from None
        raise
    with contextlib.suppress(OSError):  # the rename itself survives a power cut (not every file system allows it)
        descriptor = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(descriptor)
        finally:
            os.close(descriptor)
    return path


def open_file(path: Path, field: str, error: type, *, follow: bool = True):
    """``path`` opened for reading as a binary file object, checked to be a regular file; with
    ``follow=False`` a link is not followed.  ``error`` names the file and ``field`` otherwise."""
    path = Path(path)
    # non-blocking, so that a FIFO planted in its place cannot hang the open; cleared below
    flags = os.O_RDONLY | os.O_NONBLOCK | (0 if follow else getattr(os, "O_NOFOLLOW", 0))
    try:
        descriptor = os.open(path, flags)
    except OSError as failure:
        if not follow and path.is_symlink():
            raise error(f"{path} ({field}) is a link, which daemodel does not follow out of the directory") from None
        raise error(f"{path} ({field}) cannot be read: {failure.strerror or failure}") from None
    if not stat.S_ISREG(os.fstat(descriptor).st_mode):
        os.close(descriptor)
        raise error(f"{path} ({field}) is not a plain file")
    os.set_blocking(descriptor, True)
    return os.fdopen(descriptor, "rb")


def is_plain_file(path: Path) -> bool:
    """Whether ``path`` is a regular file itself (not a link, a FIFO or a device)."""
    try:
        return stat.S_ISREG(os.lstat(path).st_mode)
    except OSError:
        return False


def open_inside(directory: Path, name, field: str, error: type):
    """The file ``name``, read from a file's contents, in ``directory``: the name is checked by
    :func:`file_name` and a link is not followed, so nothing outside ``directory`` is read."""
    return open_file(Path(directory) / file_name(name, field, error), field, error, follow=False)


def stored_members(handle, path, error: type, limit: int | None = None, what: str = "daemodel file") -> dict:
    """The members of the zip archive ``handle`` (``path`` for messages) by name, with their sizes,
    after checking that each is stored uncompressed (daemodel writes no compressed archive, so a
    compressed member is a foreign file, or a bomb) and that together they fit in the file's real
    size and ``limit`` bytes; else ``error`` naming the file and the member."""
    size = os.fstat(handle.fileno()).st_size
    try:
        with zipfile.ZipFile(handle) as archive:
            members = archive.infolist()
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as failure:
        raise error(f"{path} is not a {what}, or is cut short ({type(failure).__name__}: {failure})") from None
    finally:
        handle.seek(0)
    sizes = {}
    for member in members:
        if member.compress_type != zipfile.ZIP_STORED:
            raise error(
                f"{path}: member {member.filename!r} is compressed; daemodel writes its files uncompressed, so this "
                "is not one of them"
            )
        sizes[member.filename] = member.file_size
    declared = sum(sizes.values())
    if declared > size:
        raise error(f"{path} declares {declared} bytes of data in a file of {size} bytes: it is damaged")
    if limit is not None and declared > limit:
        raise error(
            f"{path} holds {_size(declared)}, more than the {_size(limit)} allowed (set {MEMORY_LIMIT_VARIABLE}, "
            "e.g. '64G', to change it)"
        )
    return sizes


def read_arrays(
    handle,
    path,
    expected: dict,
    error: type,
    limit: int | None = None,
    what: str = "daemodel file",
    *,
    data: bool = True,
    others: bool = False,
) -> dict:
    """The arrays of the ``.npz`` archive ``handle`` (``path`` for messages), exactly the members
    ``expected`` names (``{name: (dtype kinds, ndim)}``, e.g. ``{"t": ("f", 1)}``).  Each member's
    header (dtype, shape) is read and checked against ``expected`` and against the member's real
    size before its data is allocated; no object arrays (no pickles).  Else ``error`` naming the
    file and the field.  With ``data=False``, only each array's shape (nothing allocated); with
    ``others=True``, other members may be there (unread: a first pass that learns which)."""
    sizes = stored_members(handle, path, error, limit, what)
    found = {name.removesuffix(".npy") if name.endswith(".npy") else name + "/" for name in sizes}
    missing, extra = [n for n in expected if n not in found], [] if others else sorted(found - set(expected))
    if missing or extra:
        problem = f"lacks the field {missing[0]!r}" if missing else f"holds a field {extra[0]!r} that it should not"
        raise error(f"{path} {problem} (a daemodel file holds {', '.join(expected)}): it is damaged or foreign")
    arrays = {}
    with zipfile.ZipFile(handle) as archive:
        for name, (kinds, ndim) in expected.items():
            try:
                with archive.open(f"{name}.npy") as member:
                    version = np.lib.format.read_magic(member)
                    fmt = np.lib.format
                    header = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
                    shape, _, dtype = header(member)
                    data_start = member.tell()
                if dtype.hasobject or dtype.kind not in kinds or len(shape) != ndim:
                    raise error(
                        f"{path}: field {name!r} is an array of {dtype} with {len(shape)} axes; "
                        f"expected {ndim} axes of kind {kinds!r}"
                    )
                needed = int(np.prod(shape, dtype=object)) * dtype.itemsize
                if needed > sizes[f"{name}.npy"] - data_start:
                    raise error(
                        f"{path}: field {name!r} declares shape {shape} ({needed} bytes) in {sizes[f'{name}.npy']} "
                        "bytes: the file is cut short or damaged"
                    )
                if not data:
                    arrays[name] = shape
                    continue
                with archive.open(f"{name}.npy") as member:
                    arrays[name] = np.lib.format.read_array(member, allow_pickle=False)
            except (ValueError, OSError, EOFError, zipfile.BadZipFile) as failure:
                if isinstance(failure, error):
                    raise
                raise error(f"{path}: field {name!r} cannot be read ({type(failure).__name__}: {failure})") from None
    handle.seek(0)
    return arrays


# How arrays and non-finite numbers travel in the JSON of a file whose arrays are members beside it
# (:func:`stored`, :func:`restored`): {"__array__": member} and {"__float__": "nan" | "inf" | "-inf"}.
ARRAY_KEY = "__array__"
FLOAT_KEY = "__float__"
# The members :func:`stored` names, and the dtype kinds it stores as arrays (numbers and flags).
STORED_NAME = re.compile(r"a[0-9]{1,9}")
STORED_KINDS = "fiub"


def stored(value, arrays: dict):
    """``value`` (dicts with string keys, lists, tuples, numbers, strings, None, numpy arrays and
    scalars) as plain JSON data: each numeric or boolean array of at least one axis moved into
    ``arrays`` under a new member name (``a0``, ``a1``, ...) and replaced by ``{ARRAY_KEY: name}``, a
    non-finite float by ``{FLOAT_KEY: "nan"}`` (JSON has no NaN); anything else by its ``str``.
    :func:`restored` undoes it."""
    if isinstance(value, np.ndarray) and value.ndim and value.dtype.kind in STORED_KINDS:
        name = f"a{len(arrays)}"
        arrays[name] = np.ascontiguousarray(value)
        return {ARRAY_KEY: name}
    if isinstance(value, np.ndarray | np.generic):
        value = value.tolist()
        if isinstance(value, list):
            return [stored(v, arrays) for v in value]
    if isinstance(value, bool) or value is None or isinstance(value, str | int):
        return value
    if isinstance(value, float):
        return value if np.isfinite(value) else {FLOAT_KEY: str(value)}
    if isinstance(value, dict):
        return {str(k): stored(v, arrays) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [stored(v, arrays) for v in value]
    return str(value)


def restored(value, arrays: dict, path, error: type, field: str):
    """The value :func:`stored` made, with its arrays from ``arrays``; ``error`` naming the file and
    ``field`` for a reference to an array that is not there."""
    if isinstance(value, list):
        return [restored(v, arrays, path, error, field) for v in value]
    if not isinstance(value, dict):
        return value
    if set(value) == {ARRAY_KEY}:
        name = value[ARRAY_KEY]
        if not isinstance(name, str) or name not in arrays:
            raise error(
                f"{path}: field {field!r} refers to an array {name!r} that the file does not hold: it is damaged"
            )
        return arrays[name]
    if set(value) == {FLOAT_KEY} and value[FLOAT_KEY] in ("nan", "inf", "-inf"):
        return float(value[FLOAT_KEY])
    return {k: restored(v, arrays, path, error, field) for k, v in value.items()}


def _depth(value, limit: int, level: int = 0) -> int:
    if level > limit:
        return level
    if isinstance(value, dict):
        return max((_depth(v, limit, level + 1) for v in value.values()), default=level + 1)
    if isinstance(value, list):
        return max((_depth(v, limit, level + 1) for v in value), default=level + 1)
    return level


def parse_json(text: str, path, error: type, what: str):
    """The JSON value of ``text`` (read from ``path``), nested at most :data:`JSON_DEPTH` levels;
    else ``error`` naming the file as not ``what``."""

    def refuse(constant):
        raise ValueError(f"{constant} is not a JSON number")

    try:
        value = json.loads(text, parse_constant=refuse)  # NaN and Infinity: daemodel writes null
    except (ValueError, RecursionError) as failure:
        raise error(f"{path} is not {what} ({type(failure).__name__}: {failure})") from None
    if _depth(value, JSON_DEPTH) > JSON_DEPTH:
        raise error(f"{path} is not {what}: it nests deeper than {JSON_DEPTH} levels")
    return value


def read_json(path: Path, error: type, what: str, *, follow: bool = True):
    """The JSON value in ``path``, read after checking its size (:data:`JSON_BYTES`, and a third of
    the memory limit: parsing takes a few times the text); else ``error`` naming the file as not
    ``what``.  ``follow=False``: a link there is refused."""
    path = Path(path)
    with open_file(path, "path", error, follow=follow) as handle:
        size, largest = os.fstat(handle.fileno()).st_size, min(JSON_BYTES, memory_limit() // 3)
        if size > largest:
            raise error(f"{path} is {_size(size)}, more than {what} holds ({_size(largest)})")
        try:
            text = handle.read().decode("utf-8")
        except (OSError, UnicodeDecodeError) as failure:
            raise error(f"{path} is not {what} ({type(failure).__name__})") from None
    return parse_json(text, path, error, what)


def write_json(path: Path, value, *, mode: int | None = None) -> Path:
    """``value`` as JSON (no NaN: strict parsers reject it), written atomically to ``path`` (``mode``:
    see :func:`atomic_write`)."""
    text = json.dumps(value, indent=1, allow_nan=False) + "\n"
    return atomic_write(path, lambda handle: handle.write(text), text=True, mode=mode)


def save_figure(fig, path, argument: str, dpi: int) -> Path:
    """A matplotlib figure written atomically to ``path`` (checked by :func:`writable_file`), in the
    format its suffix names (PNG without one)."""
    path = writable_file(path, argument)
    fmt = path.suffix[1:].lower() or "png"
    if fmt not in fig.canvas.get_supported_filetypes():
        known = ", ".join(sorted(fig.canvas.get_supported_filetypes()))
        raise InvalidOptionError(f"{argument} = '{path}': matplotlib writes no '.{fmt}' files; use one of {known}")
    return atomic_write(path, lambda handle: fig.savefig(handle, format=fmt, dpi=dpi))


class DirectoryLock:
    """An exclusive lock on ``directory`` for one writer, held from :meth:`acquire` to
    :meth:`release` (or the end of the process): a file ``.daemodel-lock`` locked with ``flock``
    and holding the holder's process, host and start time.  A second writer, in this process or
    another, gets ``error`` naming the holder and how to clear a lock that outlived its process
    (possible on a network file system, where ``flock`` may not reach other hosts)."""

    NAME = ".daemodel-lock"

    def __init__(self, directory: Path, argument: str, error: type = InvalidOptionError):
        self.path, self.argument, self.error = Path(directory) / self.NAME, argument, error
        self._descriptor = None

    def acquire(self) -> DirectoryLock:
        import fcntl

        for _ in range(100):  # the holder may remove the file between our open and our lock: retry
            try:
                descriptor = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o644)
            except OSError as failure:
                raise self.error(
                    f"{self.argument} {self.path.parent} cannot be locked: {self.path}: {failure.strerror or failure}"
                ) from None
            try:
                fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                holder = os.read(descriptor, 4096).decode("utf-8", "replace").strip() or "a process starting"
                os.close(descriptor)
                raise self.error(
                    f"{self.argument} {self.path.parent} is being written by another run ({holder}); wait for it to "
                    f"finish, or, if no such process runs (a lock left on a network file system), remove {self.path}"
                ) from None
            try:
                same = os.stat(self.path, follow_symlinks=False).st_ino == os.fstat(descriptor).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(descriptor)
        else:
            raise self.error(f"{self.argument} {self.path.parent}: its lock file keeps changing; is another run there?")
        self._descriptor = descriptor
        try:
            os.ftruncate(descriptor, 0)
            holder = f"process {os.getpid()} on {socket.gethostname()} since {time.strftime('%c')}"
            os.write(descriptor, holder.encode())
        except OSError as failure:
            self.release()
            raise FileWriteError(f"{self.path} could not be written: {failure.strerror or failure}") from None
        return self

    def release(self) -> None:
        if self._descriptor is not None:
            with contextlib.suppress(OSError):
                os.unlink(self.path)  # before closing: a waiting writer then finds the file gone and retries
            os.close(self._descriptor)
            self._descriptor = None

    def __enter__(self) -> DirectoryLock:
        return self.acquire()

    def __exit__(self, *_) -> None:
        self.release()
