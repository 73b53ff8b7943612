"""The disk cache of compiled libraries (daemodel/cache.py): safe, atomic, concurrent, bounded, stale-proof.

Each test has its own cache folder (``DAEMODEL_CACHE`` set to a fresh temporary path).  Small casadi
functions go through :func:`daemodel.cache.cached_library` directly (a compile of ~0.1 s); solves with
``jit=True`` show what a user sees: ``stats["compiled_cache"]``, the warning, the same numbers.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from daemodel.backends.radau.compiled import COMPILER_FLAGS, find_compiler

import daemodel as dm
from daemodel import cache
from daemodel.comparing.cli import main
from daemodel.errors import CacheWarning, CompileError, InvalidOptionError, UnsafeCacheError
from daemodel.problems import PROBLEMS

pytestmark = pytest.mark.skipif(find_compiler() is None, reason="no C compiler on PATH")

FIX = "solve with jit=False"


@pytest.fixture
def folder(tmp_path, monkeypatch) -> Path:
    """A fresh cache folder for this test (not yet created)."""
    path = tmp_path / "cache"
    monkeypatch.setenv(cache.CACHE_VARIABLE, str(path))
    monkeypatch.delenv(cache.SIZE_VARIABLE, raising=False)
    monkeypatch.delenv(cache.TIMEOUT_VARIABLE, raising=False)
    return path


def source(factor: float) -> tuple[str, str]:
    """C source of ``f(x) = factor * x + x * x`` (x of 3) by casadi's code generator, and the function's name."""
    import casadi

    x = casadi.SX.sym("x", 3)
    generator = casadi.CodeGenerator("daemodel_jit")
    generator.add(casadi.Function("scaled", [x], [factor * x + x * x]))
    return generator.dump(), "scaled"


def build(compiler: str | None = None, flags=COMPILER_FLAGS) -> cache.Build:
    return cache.Build(compiler or find_compiler(), flags, "compiling", FIX)


def key(factor: float, compiler: str | None = None) -> str:
    return cache.entry_key(source(factor)[0], build(compiler))


def compiled(factor: float, compiler: str | None = None) -> cache.Library:
    code, name = source(factor)
    return cache.cached_library(code, [name], build(compiler))


def evaluates(library: cache.Library, factor: float) -> bool:
    """Whether the loaded function is ``factor * x + x * x`` (the one its source says: exact here)."""
    x = np.array([0.5, -1.0, 2.0])
    return np.array_equal(np.asarray(library.functions["scaled"](x)).ravel(), factor * x + x * x)


def files(path: Path) -> dict:
    return {p.name: p.read_bytes() for p in sorted(path.iterdir())} if path.exists() else {}


def pendulum_jit(**options):
    return dm.solve(PROBLEMS["pendulum"].model(), (0.0, 1.0), jit=True, h=0.05, **options)


# -- where it is -------------------------------------------------------------------------------------


def test_the_folder_is_daemodel_cache_else_the_users_cache_folder(tmp_path, monkeypatch):
    monkeypatch.setenv("DAEMODEL_CACHE", str(tmp_path / "here"))
    assert cache.cache_folder() == tmp_path / "here"
    monkeypatch.delenv("DAEMODEL_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache.cache_folder() == tmp_path / "xdg" / "daemodel"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cache.cache_folder() == tmp_path / "home" / ".cache" / "daemodel"


def test_the_test_suite_never_uses_the_users_cache(compiled_cache):
    assert Path(os.environ["DAEMODEL_CACHE"]) == compiled_cache
    assert Path.home() / ".cache" not in compiled_cache.parents


def test_the_size_limit_is_read_from_the_environment(monkeypatch):
    monkeypatch.delenv("DAEMODEL_CACHE_SIZE", raising=False)
    assert cache.size_limit() == 1 << 30
    monkeypatch.setenv("DAEMODEL_CACHE_SIZE", "12345")
    assert cache.size_limit() == 12345
    monkeypatch.setenv("DAEMODEL_CACHE_SIZE", "2M")
    assert cache.size_limit() == 2 << 20
    monkeypatch.setenv("DAEMODEL_CACHE_SIZE", "lots")
    with pytest.raises(InvalidOptionError, match=r"DAEMODEL_CACHE_SIZE = 'lots' is not a size; give bytes"):
        cache.size_limit()


def test_the_folder_is_created_private_with_its_parents(folder):
    nested = folder / "a" / "b"
    os.environ["DAEMODEL_CACHE"] = str(nested)
    assert evaluates(compiled(2.0), 2.0)
    assert nested.stat().st_mode & 0o777 == 0o700
    assert all((nested / name).stat().st_mode & 0o777 == 0o600 for name in files(nested))


def test_the_folders_it_creates_above_it_are_private_under_any_umask(folder):
    """Under umask 002 (user-private groups) ``mkdir -p``'s parents came out 775: the cache then refused
    itself on every later run (a folder above it writable by the group), the first run used it."""
    nested = folder / "a" / "b"
    os.environ["DAEMODEL_CACHE"] = str(nested)
    before = os.umask(0o002)
    try:
        assert compiled(2.0).outcome == "miss"
        assert compiled(2.0).outcome == "hit"
    finally:
        os.umask(before)
    assert [oct(path.stat().st_mode & 0o777) for path in (folder, folder / "a", nested)] == ["0o700"] * 3


# -- a miss, then a hit; the key -----------------------------------------------------------------------


def test_a_miss_stores_the_library_and_its_stamp_and_the_next_load_hits(folder):
    first = compiled(2.0)
    assert first.outcome == "miss" and evaluates(first, 2.0)
    name = key(2.0)
    assert sorted(files(folder)) == [name + ".json", name + ".so"]
    stamp = json.loads((folder / (name + ".json")).read_text())
    assert stamp == {
        "key": name,
        "source": cache.digest(source(2.0)[0]),
        "library": cache.digest((folder / (name + ".so")).read_bytes()),
    }
    second = compiled(2.0)
    assert second.outcome == "hit" and evaluates(second, 2.0)


def test_the_key_changes_with_the_source_compiler_flags_and_versions(monkeypatch):
    code, first = source(2.0)[0], key(2.0)
    assert key(2.0) == first  # the same source: the same key
    assert key(2.5) != first
    assert cache.entry_key(code, build(flags=("-O3",))) != first
    assert cache.entry_key(code, build(find_compiler() + "x")) != first
    assert cache.entry_key(code, build()._replace(libraries=("-lm",))) != first
    monkeypatch.setattr(cache, "compiler_version", lambda compiler: "cc (Debian 99.0.0) 99.0.0")
    assert key(2.0) != first
    monkeypatch.undo()
    monkeypatch.setattr(cache, "versions", lambda: ("3.8.2", "0.2.0"))
    assert key(2.0) != first


def test_a_changed_coefficient_is_a_new_entry_and_a_new_answer(folder):
    """Stale-proof: the model x' = -k x with k written into its equation (no parameter: the code changes)."""

    def decay(k: float) -> dm.Model:
        m = dm.Model("decay")
        m.states("x")
        m.ode("x", f"-{k} * x")
        m.initial(x=1.0)
        return m

    options = dict(jit=True, rtol=1e-10, atol=1e-12)
    first = dm.solve(decay(2.0), (0.0, 1.0), **options)
    changed = dm.solve(decay(2.5), (0.0, 1.0), **options)
    again = dm.solve(decay(2.0), (0.0, 1.0), **options)
    assert first.stats["compiled_cache"] == "miss"
    assert changed.stats["compiled_cache"] == "miss"  # a new key: the old library is not found
    assert again.stats["compiled_cache"] == "hit"
    assert abs(first["x"][-1] - np.exp(-2.0)) < 1e-8
    assert abs(changed["x"][-1] - np.exp(-2.5)) < 1e-8
    assert abs(changed["x"][-1] - first["x"][-1]) > 0.05
    assert np.array_equal(again["x"], first["x"])


# -- safe ----------------------------------------------------------------------------------------------


def test_a_planted_link_as_the_folder_is_refused(folder, tmp_path):
    target = tmp_path / "elsewhere"
    target.mkdir(mode=0o700)
    folder.symlink_to(target)
    with pytest.raises(UnsafeCacheError, match=rf"cache folder {folder} is a symbolic link; set DAEMODEL_CACHE"):
        cache.checked_folder()
    with pytest.warns(CacheWarning, match=r"is a symbolic link.*compiled code is kept for this process only"):
        library = compiled(2.0)
    assert library.outcome.startswith("refused: cache folder") and evaluates(library, 2.0)
    assert files(target) == {}  # nothing written through the link


def test_a_planted_link_in_the_folder_is_refused_and_nothing_is_loaded_from_it(folder, tmp_path):
    """An entry's library replaced by a link to another library (with a stamp to match): never loaded."""
    first = compiled(2.0)
    name = key(2.0)
    planted = tmp_path / "planted.so"
    planted.write_bytes((folder / (name + ".so")).read_bytes())
    os.unlink(folder / (name + ".so"))
    (folder / (name + ".so")).symlink_to(planted)
    with pytest.raises(UnsafeCacheError, match=rf"cache folder {folder}: {name}.so is a symbolic link; remove it"):
        cache.checked_folder()
    with pytest.warns(CacheWarning, match="is a symbolic link"):
        again = compiled(2.0)
    assert first.outcome == "miss" and again.outcome.startswith("refused:") and evaluates(again, 2.0)
    assert (folder / (name + ".so")).is_symlink()  # the refused folder is left as it was


@pytest.mark.parametrize(
    ("mode", "what", "match"),
    [
        (0o770, "folder", r"cache folder .* is writable by the group \(mode 770\)"),
        (0o707, "folder", r"cache folder .* is writable by others \(mode 707\)"),
        (0o777, "folder", r"cache folder .* is writable by the group and others \(mode 777\)"),  # (said "the group")
        (0o620, "file", r"cache folder .*: [0-9a-f]{64}\.json is writable by the group \(mode 620\); remove it"),
        (0o602, "file", r"cache folder .*: [0-9a-f]{64}\.so is writable by others \(mode 602\)"),
    ],
)
def test_a_folder_or_file_writable_by_others_is_refused(folder, mode, what, match):
    compiled(2.0)
    if what == "folder":
        folder.chmod(mode)
    else:
        suffix = ".json" if mode & 0o020 else ".so"
        next(folder.glob("*" + suffix)).chmod(mode)
    with pytest.raises(UnsafeCacheError, match=match):
        cache.checked_folder()
    before = files(folder)
    with pytest.warns(CacheWarning, match=match):
        library = compiled(2.0)
    assert library.outcome.startswith("refused:") and evaluates(library, 2.0)
    assert files(folder) == before


def test_a_folder_of_another_user_is_refused(folder, monkeypatch):
    compiled(2.0)
    me = os.geteuid()
    monkeypatch.setattr(os, "geteuid", lambda: me + 1)
    with pytest.raises(UnsafeCacheError, match=rf"cache folder {folder} is owned by another user \(uid {me}, not"):
        cache.checked_folder()


@pytest.mark.parametrize(("mode", "who"), [(0o777, "the group and others"), (0o775, "the group"), (0o757, "others")])
def test_a_folder_above_that_others_can_write_without_the_sticky_bit_is_refused(tmp_path, monkeypatch, mode, who):
    """A parent writable by others could have the cache renamed away and a folder of theirs put in its place:
    refused before anything is created or loaded, as an unsafe folder is; /tmp's 1777 (sticky) is not."""
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(mode)
    folder = shared / "deeper" / "cache"
    monkeypatch.setenv(cache.CACHE_VARIABLE, str(folder))
    match = (
        rf"cache folder {folder}: the folder {shared} above it is writable by {who} without the sticky bit "
        rf"\(mode {mode:o}\): they could replace the cache; set DAEMODEL_CACHE to a folder under one only you"
    )
    with pytest.raises(UnsafeCacheError, match=match):
        cache.checked_folder()
    with pytest.warns(CacheWarning, match=match):
        library = compiled(2.0)
    assert library.outcome.startswith("refused: cache folder") and evaluates(library, 2.0)
    assert list(shared.iterdir()) == []  # (nothing created under it)
    shared.chmod(mode | 0o1000)  # (sticky, as /tmp: only a name's owner may rename it)
    assert cache.checked_folder() == folder and folder.is_dir()
    assert compiled(2.0).outcome == "miss"


def test_a_folder_above_is_checked_where_links_lead(tmp_path, monkeypatch):
    """The folders checked are those of the resolved path: a link from a private folder into a shared one."""
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    (shared / "real").mkdir(mode=0o700)
    private = tmp_path / "private"
    private.mkdir(mode=0o700)
    (private / "link").symlink_to(shared / "real")
    folder = private / "link" / "cache"
    with pytest.raises(UnsafeCacheError, match=rf"the folder {shared} above it is writable by the group and others"):
        cache.checked_folder(folder)


@pytest.mark.skipif(os.geteuid() != 0, reason="giving a folder or a link to another user takes root")
def test_a_folder_or_link_above_of_another_user_is_refused(tmp_path):
    theirs = tmp_path / "theirs"
    theirs.mkdir(mode=0o755)
    os.chown(theirs, 65534, -1)
    with pytest.raises(UnsafeCacheError, match=rf"the folder {theirs} above it is owned by another user \(uid 65534\)"):
        cache.checked_folder(theirs / "cache")
    mine = tmp_path / "mine"
    mine.mkdir(mode=0o700)
    link = tmp_path / "link"
    link.symlink_to(mine)
    os.lchown(link, 65534, -1)
    with pytest.raises(UnsafeCacheError, match=rf"the link {link} on its path is owned by another user \(uid 65534\)"):
        cache.checked_folder(link / "cache")
    assert cache.checked_folder(mine / "cache") == mine / "cache"


@pytest.mark.skipif(os.geteuid() != 0, reason="giving a file to another user takes root")
def test_a_file_of_another_user_is_refused(folder):
    compiled(2.0)
    stamp = next(folder.glob("*.json"))
    os.chown(stamp, 65534, -1)
    with pytest.raises(UnsafeCacheError, match=rf"{stamp.name} is owned by another user \(uid 65534, not 0\)"):
        cache.checked_folder()


def test_a_refused_folder_is_said_once_per_process_and_in_the_solves_stats(folder, recwarn):
    folder.mkdir(mode=0o777)
    folder.chmod(0o777)
    first, second = pendulum_jit(), pendulum_jit()
    said = [w for w in recwarn.list if issubclass(w.category, CacheWarning)]
    assert len(said) == 1 and "writable by the group" in str(said[0].message)
    assert first.stats["compiled_cache"].startswith("refused: cache folder")
    assert second.stats["compiled_cache"].startswith("refused: cache folder")
    assert files(folder) == {}
    vm = dm.solve(PROBLEMS["pendulum"].model(), (0.0, 1.0), h=0.05)
    for name in vm.names:
        assert np.array_equal(first[name], vm[name]), name  # (fixed steps: machine code gives the same bits)


def test_a_stored_source_hash_that_differs_is_never_loaded(folder):
    """Entry B holds A's library with A's (true) hashes: B's source is not A's, so it is compiled."""
    compiled(2.0)
    key_a, key_b = key(2.0), key(3.0)
    (folder / (key_b + ".so")).write_bytes((folder / (key_a + ".so")).read_bytes())
    stamp = json.loads((folder / (key_a + ".json")).read_text())
    (folder / (key_b + ".json")).write_text(json.dumps(dict(stamp, key=key_b)))
    for path in folder.iterdir():
        path.chmod(0o600)
    library = compiled(3.0)
    assert library.outcome == "miss (its stamp's source hash differs from the source just generated)"
    assert evaluates(library, 3.0)
    assert compiled(3.0).outcome == "hit"  # (the entry was replaced by the right one)


def test_a_library_whose_bytes_differ_from_its_stamp_is_never_loaded(folder):
    compiled(2.0)
    library = next(folder.glob("*.so"))
    library.write_bytes(library.read_bytes() + b"\0")
    again = compiled(2.0)
    assert again.outcome == "miss (its library's bytes differ from its stamp's hash)" and evaluates(again, 2.0)
    assert compiled(2.0).outcome == "hit"


# -- atomic, concurrent --------------------------------------------------------------------------------

CHILD = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    import numpy as np
    from daemodel import cache
    sys.path.insert(0, {tests!r})
    from test_cache import compiled, evaluates
    Path(sys.argv[1] + ".ready").touch()
    while not Path(sys.argv[2]).exists():
        time.sleep(0.01)
    library = compiled(2.0, {compiler!r})
    print(library.outcome, evaluates(library, 2.0))
    """
)


def child(tmp_path: Path, compiler: str | None = None) -> Path:
    script = tmp_path / "child.py"
    script.write_text(CHILD.format(tests=str(Path(__file__).parent), compiler=compiler))
    return script


def test_two_processes_compiling_at_once_both_succeed_and_one_library_wins(folder, tmp_path):
    script, go = child(tmp_path), tmp_path / "go"
    runs = [
        subprocess.Popen(
            [sys.executable, str(script), str(tmp_path / f"p{i}"), str(go)], stdout=subprocess.PIPE, text=True
        )
        for i in range(2)
    ]
    deadline = time.monotonic() + 120
    while not all((tmp_path / f"p{i}.ready").exists() for i in range(2)) and time.monotonic() < deadline:
        time.sleep(0.01)
    go.touch()  # both compile now
    outputs = [run.communicate(timeout=120)[0].split() for run in runs]
    assert all(run.returncode == 0 for run in runs)
    assert sorted(out[1] for out in outputs) == ["True", "True"]
    assert {out[0] for out in outputs} <= {"miss", "hit"}
    name = key(2.0)
    assert sorted(files(folder)) == [name + ".json", name + ".so"]  # one entry, no temporary file left
    assert compiled(2.0).outcome == "hit"


def test_a_process_killed_while_compiling_leaves_nothing_that_is_loaded(folder, tmp_path):
    """kill -9 of a child (and its compiler) mid-compile; then a fresh process compiles and loads."""
    slow = tmp_path / "slowcc"
    marker = tmp_path / "compiling"
    slow.write_text(
        f'#!/bin/sh\nif [ -n "$SLOW" ] && [ "$1" != --version ]; then touch {marker}; sleep 60; fi\n'
        f'exec {find_compiler()} "$@"\n'
    )
    slow.chmod(0o755)
    script, go = child(tmp_path, str(slow)), tmp_path / "go"
    go.touch()
    run = subprocess.Popen(
        [sys.executable, str(script), str(tmp_path / "p"), str(go)],
        env={**os.environ, "SLOW": "1", "TMPDIR": str(tmp_path)},
        start_new_session=True,
        stdout=subprocess.PIPE,
    )
    deadline = time.monotonic() + 120
    while not marker.exists() and time.monotonic() < deadline and run.poll() is None:
        time.sleep(0.01)
    assert marker.exists()
    os.killpg(run.pid, signal.SIGKILL)
    run.wait(timeout=30)
    assert run.returncode == -signal.SIGKILL
    assert not [name for name in files(folder) if name.endswith(".json")]  # no stamp: nothing loadable
    # a kill during a store leaves a temporary file or an unstamped library: planted here, both ignored
    name = key(2.0, str(slow))
    (folder / f".{name}.so.x1y2z3.partial").write_bytes(b"half a library")
    (folder / f"{name}.so").write_bytes(b"not a library")
    for path in folder.iterdir():
        path.chmod(0o600)
    fresh = subprocess.run(
        [sys.executable, str(script), str(tmp_path / "q"), str(go)], capture_output=True, text=True, timeout=120
    )
    assert fresh.returncode == 0, fresh.stderr
    assert fresh.stdout.split() == ["miss", "True"]
    assert (folder / f".{name}.so.x1y2z3.partial").exists()  # (young: it may be a write in progress)
    assert main(["cache", "clear"]) == 0
    assert files(folder) == {}


def test_a_full_disk_leaves_the_cache_unchanged_and_the_solve_succeeds(folder, monkeypatch):
    compiled(5.0)  # something in the cache already
    before = files(folder)

    def full(descriptor):
        raise OSError(errno.ENOSPC, "No space left on device")

    with monkeypatch.context() as patch:
        patch.setattr(os, "fsync", full)
        with pytest.warns(CacheWarning, match=r"could not store a compiled library \(.*No space left on device"):
            sol = pendulum_jit()
    assert sol.stats["compiled_cache"].startswith("not stored: ")
    assert files(folder) == before
    vm = dm.solve(PROBLEMS["pendulum"].model(), (0.0, 1.0), h=0.05)
    for name in vm.names:
        assert np.array_equal(sol[name], vm[name]), name


def test_a_full_temporary_folder_is_a_compile_error_and_auto_goes_on_on_the_virtual_machine(folder, monkeypatch):
    """The C source written where the compiler runs (TMPDIR) on a full disk or past a file-size limit
    (``ulimit -f 50``): before, a bare OSError ("File too large") out of dm.solve, jit="auto" included."""
    write_text = Path.write_text

    def full(path, *args, **kwargs):
        if path.parent.name.startswith("daemodel-jit-"):
            raise OSError(errno.EFBIG, "File too large")
        return write_text(path, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", full)
    said = r"its C source could not be written in .*daemodel-jit-.* \(File too large\); free space there or set TMPDIR"
    with pytest.raises(CompileError, match=said + " to another folder, or solve with jit=False"):
        pendulum_jit()
    sol = dm.solve(PROBLEMS["pendulum"].model(), (0.0, 1.0), h=0.05)  # (jit="auto")
    assert (
        sol.stats["jit"].startswith("casadi's virtual machine: the C compiler failed (")
        and "File too large" in (sol.stats["jit"])
    )
    assert files(folder) == {}


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="names an open file through /proc")
def test_a_stamp_that_cannot_be_written_takes_its_library_away(folder, monkeypatch):
    real = os.fsync

    def stamp_fails(descriptor):  # the library's write succeeds, the stamp's does not
        if ".json." in os.readlink(f"/proc/self/fd/{descriptor}"):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(descriptor)

    monkeypatch.setattr(os, "fsync", stamp_fails)
    with pytest.warns(CacheWarning, match="could not store"):
        library = compiled(2.0)
    assert library.outcome.startswith("not stored: ") and evaluates(library, 2.0)
    assert files(folder) == {}


# -- bounded -------------------------------------------------------------------------------------------


def test_eviction_goes_least_recently_used_first(folder, monkeypatch):
    compiled(2.0)
    compiled(3.0)
    keys = {factor: key(factor) for factor in (2.0, 3.0, 4.0)}
    sizes = cache.entries(folder)["entries"]
    now = time.time()
    os.utime(folder / (keys[2.0] + ".json"), (now - 100, now - 100))
    os.utime(folder / (keys[3.0] + ".json"), (now - 50, now - 50))
    assert compiled(2.0).outcome == "hit"  # 2.0 used last now, 3.0 the least recently
    largest = max(size for size, _ in sizes.values())
    monkeypatch.setenv("DAEMODEL_CACHE_SIZE", str(2 * largest + largest // 2))
    old = folder / f".{keys[3.0]}.json.old.partial"
    young = folder / f".{keys[3.0]}.json.young.partial"
    for path in (old, young):
        path.write_bytes(b"x")
        path.chmod(0o600)
    os.utime(old, (now - 2 * cache.PARTIAL_GRACE, now - 2 * cache.PARTIAL_GRACE))
    assert compiled(4.0).outcome == "miss"
    assert set(cache.entries(folder)["entries"]) == {keys[2.0], keys[4.0]}
    assert not old.exists() and young.exists()
    assert compiled(3.0).outcome == "miss"  # evicted: compiled again


def test_an_entry_above_the_limit_is_not_kept(folder, monkeypatch):
    monkeypatch.setenv("DAEMODEL_CACHE_SIZE", "100")
    assert compiled(2.0).outcome == "miss" and files(folder) == {}


# -- the commands --------------------------------------------------------------------------------------


def test_cache_info_and_clear(folder, capsys):
    assert main(["cache", "info"]) == 0
    assert "safe:             yes (not created yet)\nentries:          0\n" in capsys.readouterr().out
    compiled(2.0)
    compiled(3.0)
    other = folder / "notes.txt"
    other.write_text("mine")
    other.chmod(0o600)
    size = sum(size for size, _ in cache.entries(folder)["entries"].values())
    assert main(["cache", "info"]) == 0
    out = capsys.readouterr().out
    assert f"folder:           {folder}\n" in out
    assert "safe:             yes\n" in out
    assert "entries:          2\n" in out
    assert f"bytes:            {size}\n" in out
    assert "limit:            1073741824\n" in out
    assert main(["cache", "clear"]) == 0
    assert capsys.readouterr().out == f"daemodel cache clear: freed {size} bytes in {folder}\n"
    assert files(folder) == {"notes.txt": b"mine"}  # daemodel's entries only
    assert main(["cache", "clear"]) == 0
    assert "freed 0 bytes" in capsys.readouterr().out


def test_cache_clear_refuses_an_unsafe_folder(folder, capsys):
    compiled(2.0)
    folder.chmod(0o777)
    before = files(folder)
    assert main(["cache", "info"]) == 0
    assert "safe:             no: cache folder" in capsys.readouterr().out
    assert main(["cache", "clear"]) == 2
    assert "daemodel cache clear: cache folder" in capsys.readouterr().err
    assert files(folder) == before


@pytest.mark.parametrize(
    "script, said",
    [
        ("exit 0", r"wrote no library"),  # (says it succeeded, writes nothing)
        ("echo 'not an ELF file' > library.so", r"its library does not load"),  # (writes garbage)
    ],
)
def test_a_compiler_that_succeeds_without_a_loadable_library_is_a_compile_error(
    folder, tmp_path, monkeypatch, script, said
):
    """A compiler that exits 0 but leaves no library, or one casadi cannot load, is a CompileError
    naming it (not a FileNotFoundError or casadi's RuntimeError), and nothing is stored; under radau's
    default jit="auto" the solve goes on on casadi's virtual machine."""
    bogus = tmp_path / "bin" / "cc"
    bogus.parent.mkdir()
    # (--version runs in the caller's folder: it writes nothing)
    bogus.write_text(f'#!/bin/sh\n[ "$1" = --version ] && exit 0\n{script}\n')
    bogus.chmod(0o755)
    with pytest.raises(CompileError, match=rf"compiling with {bogus} failed: .*{said}.*; {FIX}"):
        compiled(2.0, compiler=str(bogus))
    assert not any(name.endswith(cache.LIBRARY) for name in files(folder))
    monkeypatch.setenv("PATH", str(bogus.parent))
    sol = dm.solve(PROBLEMS["pendulum"].model(), (0.0, 1.0), h=0.05)
    assert sol.stats["jit"].startswith("casadi's virtual machine: the C compiler failed") and said in sol.stats["jit"]
    assert sol.status == "success" and not any(name.endswith(cache.LIBRARY) for name in files(folder))


@pytest.mark.parametrize("units", [1, 3])
def test_a_compiler_past_its_time_is_stopped(tmp_path, monkeypatch, units):
    """A compiler run (or each of the units' runs at once) that takes longer than the build's timeout is
    stopped, and the CompileError says so; a compiler that cannot be started is named likewise."""
    slow = tmp_path / "bin" / "cc"
    slow.parent.mkdir()
    slow.write_text(f'#!/bin/sh\n[ "$1" = --version ] && exit 0\necho $$ >> {tmp_path / "pids"}\nexec sleep 60\n')
    slow.chmod(0o755)
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.setattr(cache, "workers", lambda: units)
    monkeypatch.delenv(cache.TIMEOUT_VARIABLE, raising=False)
    source = "\n".join(f"double f{k}(double x) {{\n  return {k} * x;\n}}" for k in range(3000))  # (~80 kB: 3 units)
    build = cache.Build(str(slow), (), "compiling", FIX, timeout=1.0, units=units)
    began = time.monotonic()
    said = r"did not finish in 1 s \(DAEMODEL_COMPILE_TIMEOUT sets the limit\)"
    with pytest.raises(CompileError, match=rf"compiling with {slow} failed: {said}; {FIX}"):
        cache.compile_library(source, work, build)
    assert time.monotonic() - began < 30
    pids = [int(pid) for pid in (tmp_path / "pids").read_text().split()]
    assert len(pids) == units
    for pid in pids:  # (stopped: no process left behind)
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)
    with pytest.raises(CompileError, match=r"compiling with .*no-such-cc failed: .*No such file"):
        cache.compile_library(source, work, build._replace(compiler=str(tmp_path / "no-such-cc")))


def test_a_hanging_compiler_is_bounded_by_daemodel_compile_timeout(folder, tmp_path, monkeypatch):
    """A compiler that hangs held radau's default jit="auto" for 60 s of ``--version`` and 600 s of compiling
    (constants a user could not change) before the virtual machine took over, on the first solve of each
    model.  DAEMODEL_COMPILE_TIMEOUT (seconds) bounds both; a value that is not a positive number is named."""
    slow = tmp_path / "bin" / "cc"
    slow.parent.mkdir()
    slow.write_text("#!/bin/sh\nexec /bin/sleep 20\n")  # (--version too)
    slow.chmod(0o755)
    monkeypatch.setenv("PATH", str(slow.parent))
    monkeypatch.setenv("DAEMODEL_COMPILE_TIMEOUT", "0.5")
    sol = dm.solve(PROBLEMS["pendulum"].model(), (0.0, 1.0), h=0.05)
    assert sol.status == "success"
    assert sol.stats["jit"].startswith("casadi's virtual machine: the C compiler failed")
    assert f"with {slow} failed: did not finish in 0.5 s (DAEMODEL_COMPILE_TIMEOUT sets the limit)" in sol.stats["jit"]
    assert cache.compiler_version(str(slow)) == "unknown (TimeoutExpired)"
    with pytest.raises(CompileError, match=r"did not finish in 0\.5 s \(DAEMODEL_COMPILE_TIMEOUT sets the limit\)"):
        dm.solve(PROBLEMS["pendulum"].model(), (0.0, 1.0), h=0.05, jit=True)
    monkeypatch.delenv("DAEMODEL_COMPILE_TIMEOUT")
    assert cache.compile_timeout(600.0) == 600.0
    for text in ("0", "-3", "soon", "nan", "inf"):
        monkeypatch.setenv("DAEMODEL_COMPILE_TIMEOUT", text)
        with pytest.raises(
            InvalidOptionError, match=rf"DAEMODEL_COMPILE_TIMEOUT = '{text}' is not a time limit; give seconds"
        ):
            cache.compile_timeout(600.0)


def test_a_bad_setting_is_named_on_every_call_not_only_on_a_miss(folder, monkeypatch):
    """DAEMODEL_CACHE_SIZE = 'lots' was read only after a compile had stored its library: the first solve
    raised and left the entry behind, and the next, a hit, succeeded with the same setting (measured:
    InvalidOptionError, then "hit").  DAEMODEL_COMPILE_TIMEOUT was read only where a compiler ran.  Both
    are read first now: every call names them, and nothing is stored."""
    monkeypatch.setenv(cache.SIZE_VARIABLE, "lots")
    with pytest.raises(InvalidOptionError, match=r"DAEMODEL_CACHE_SIZE = 'lots' is not a size"):
        compiled(2.0)
    assert not any(name.endswith(cache.LIBRARY) for name in files(folder))
    monkeypatch.delenv(cache.SIZE_VARIABLE)
    assert compiled(2.0).outcome == "miss"
    for variable, value, said in [(cache.SIZE_VARIABLE, "lots", "a size"), (cache.TIMEOUT_VARIABLE, "soon", "a time")]:
        monkeypatch.setenv(variable, value)
        with pytest.raises(InvalidOptionError, match=rf"{variable} = '{value}' is not {said}"):
            compiled(2.0)
        monkeypatch.delenv(variable)
    assert compiled(2.0).outcome == "hit"
