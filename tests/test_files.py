"""Files under faults and hostile input (daemodel/files.py and its users): atomic writes that a
full disk or kill -9 cannot tear, names that cannot leave the user's directory, loaders that
check every field and size before they allocate, and ensembles that lock, resume and refuse
foreign chunks.  Faults that end a process (a file-size limit, kill -9, a memory limit) are
played in child processes."""

from __future__ import annotations

import dataclasses
import inspect
import json
import os
import re
import signal
import subprocess
import sys
import textwrap
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

import daemodel as dm
from daemodel.errors import (
    ComparisonError,
    FileWriteError,
    InvalidOptionError,
    NetworkFileError,
    ResourceLimitError,
    SolutionFileError,
)
from daemodel.problems import PENDULUM

TINY = dm.PINNConfig(width=8, tol=None, iterations=3, warm_start=False)
K = np.linspace(0.5, 2.0, 40)


def decay_model():
    """x' = -k x, x(0) = 1."""
    m = dm.Model("decay")
    (x,) = m.states("x")
    k = m.parameter("k", 1.0)
    m.ode(x, -k * x)
    m.initial(x=1.0)
    return m.compile()


def run_ensemble(directory="ens"):
    """40 samples in chunks of one, to a directory."""
    return dm.ensemble(decay, (0.0, 1.0), h=0.01, parameters={"k": K}, chunk=1, write_to=directory)


decay = decay_model()
# What a child process starts with: the same model and ensemble, from their source.
PRELUDE = "\n".join(
    [
        "import numpy as np",
        "import daemodel as dm",
        inspect.getsource(decay_model),
        "decay = decay_model()",
        "K = np.linspace(0.5, 2.0, 40)",
        inspect.getsource(run_ensemble),
    ]
)


def child(code: str, tmp_path: Path, *, wait: bool = True, timeout: float = 120):
    """Run ``code`` (after :data:`PRELUDE`) in a fresh Python with the working directory ``tmp_path``."""
    script = tmp_path / f"child-{time.monotonic_ns()}.py"
    script.write_text(PRELUDE + "\n" + textwrap.dedent(code))
    command = [sys.executable, str(script)]
    if not wait:
        return subprocess.Popen(command, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    done = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


@pytest.fixture(scope="module")
def saved(tmp_path_factory) -> dict:
    """One file of each kind daemodel writes, with the model that reads it."""
    root = tmp_path_factory.mktemp("kinds")
    solution = dm.solve(decay, (0.0, 1.0), h=0.1, parameters={"k": [1.0, 2.0]})
    comparison = dm.compare(PENDULUM.model(), (0.0, 0.1), ["radau"], points=1, progress=False)
    pendulum = PENDULUM.model().compile()
    dm.solve(pendulum, (0.0, 0.1), method="pinn", config=TINY, save=root / "networks.pt")
    files = dm.ensemble(decay, (0.0, 1.0), h=0.1, parameters={"k": [1.0, 2.0, 3.0]}, chunk=2, write_to=root / "ens")
    return {
        "solution": (solution.save(root / "solution.npz"), lambda p: dm.Solution.load(p, decay), SolutionFileError),
        "comparison": (comparison.to_json(root / "comparison.json"), dm.Comparison.load, ComparisonError),
        "networks": (root / "networks.pt", lambda p: dm.Surrogate.load(p, pendulum), NetworkFileError),
        "chunk": (files.directory / "chunk-000000000000.npz", lambda p: dm.Solution.load(p, decay), SolutionFileError),
        "manifest": (
            files.directory / "ensemble.json",
            lambda p: dm.EnsembleFiles.load(p.parent, decay),
            SolutionFileError,
        ),
    }


# ---- truncation -----------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["solution", "comparison", "networks", "chunk", "manifest"])
def test_a_file_cut_anywhere_is_refused_by_name(saved, kind, tmp_path):
    """Cut at 25 points (the first byte to the last but one of its content): never a raw
    exception, never a file that loads as complete."""
    path, load, error = saved[kind]
    content = path.read_bytes().rstrip()
    target = tmp_path / path.name
    if kind == "manifest":  # the manifest's chunks beside it, so that only the manifest is cut
        for chunk in path.parent.glob("chunk-*.npz"):
            (tmp_path / chunk.name).write_bytes(chunk.read_bytes())
    for cut in np.unique(np.linspace(0, len(content) - 1, 25).astype(int)):
        target.write_bytes(content[:cut])
        with pytest.raises(error, match=target.name):
            load(target)


# ---- a full disk, kill -9 -------------------------------------------------------------------------
def test_a_full_disk_leaves_every_previous_file_intact(tmp_path):
    """RLIMIT_FSIZE stands in for a full disk: each writer raises FileWriteError naming the file,
    the previous file keeps its bytes, and no temporary file is left."""
    out = child(
        """
        import json, resource, signal
        import numpy as np
        from daemodel.errors import FileWriteError
        from daemodel.problems import PENDULUM
        small = dm.solve(decay, (0.0, 1.0), h=0.1)
        big = dm.solve(decay, (0.0, 1.0), h=0.001, parameters={"k": np.linspace(1, 2, 50)})
        comparison = dm.compare(PENDULUM.model(), (0.0, 0.1), ["radau"], points=1, progress=False)
        small.save("solution.npz")
        comparison.to_json("comparison.json")
        comparison.to_csv("comparison.csv")
        small.plot("plot.png")
        names = ("solution.npz", "comparison.json", "comparison.csv", "plot.png")
        before = {name: open(name, "rb").read() for name in names}
        limit = 2 * max(map(len, before.values()))
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails with EFBIG instead of killing us
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
        import dataclasses
        long = dataclasses.replace(comparison, runs=comparison.runs * 2000)  # too long for the limit
        caught = {}
        for name, write in [
            ("solution.npz", lambda: big.save("solution.npz")),
            ("comparison.json", lambda: long.to_json("comparison.json")),
            ("comparison.csv", lambda: long.to_csv("comparison.csv")),
            ("plot.png", lambda: big.plot("plot.png")),
        ]:
            try:
                write()
                caught[name] = "written"
            except FileWriteError as error:
                caught[name] = str(error)
        import os
        intact = {name: open(name, "rb").read() == data for name, data in before.items()}
        print(json.dumps({"caught": caught, "intact": intact, "left": sorted(os.listdir("."))}))
        """,
        tmp_path,
    )
    report = json.loads(out.splitlines()[-1])
    for name, message in report["caught"].items():
        if name == "plot.png" and message == "written":
            continue  # a plot may fit the limit; then it was replaced whole
        assert f"{name} could not be written" in message and "previous contents" in message, message
        assert report["intact"][name], name
    assert not [name for name in report["left"] if name.endswith(".partial")], report["left"]


def test_kill_9_during_writes_leaves_a_complete_file(tmp_path):
    """A child saves two different solutions over one file in a loop; killed at any moment, the
    file loads as one of the two, whole."""
    proc = child(
        """
        import numpy as np, sys
        a = dm.solve(decay, (0.0, 1.0), h=0.001, parameters={"k": np.linspace(1, 2, 20)})
        b = dm.solve(decay, (0.0, 1.0), h=0.002, parameters={"k": np.linspace(3, 4, 40)})
        a.save("target.npz")
        print("ready", flush=True)
        while True:
            b.save("target.npz")
            a.save("target.npz")
        """,
        tmp_path,
        wait=False,
    )
    assert proc.stdout.readline().strip() == "ready"
    for pause in (0.05, 0.13, 0.29):
        time.sleep(pause)
        proc.send_signal(signal.SIGSTOP)  # freeze it mid-write, read, and go on
        loaded = dm.Solution.load(tmp_path / "target.npz", decay)
        assert loaded.batch_size in (20, 40) and loaded["x"].shape == (loaded.batch_size, len(loaded.t))
        proc.send_signal(signal.SIGCONT)
    proc.kill()
    proc.wait()
    loaded = dm.Solution.load(tmp_path / "target.npz", decay)
    k = loaded.parameters[:, 0]
    np.testing.assert_allclose(loaded["x"][:, -1], np.exp(-k), rtol=1e-9)


# A child's ensemble chunks, each slowed down so that the parent can act between them.
SLOW_CHUNKS = """
import time, importlib
module = importlib.import_module("daemodel.solving.ensemble")  # the module, not the function daemodel exports
original = module.solve_chunk
def slow(*args):
    time.sleep({pause})
    return original(*args)
module.solve_chunk = slow
"""


def test_kill_9_during_an_ensemble_then_the_same_call_resumes(tmp_path):
    """The first run is killed after a few chunks; the same call keeps those chunks (their files
    untouched), solves the rest, and every sample equals the exact solution."""
    proc = child(SLOW_CHUNKS.format(pause=0.15) + "run_ensemble()", tmp_path, wait=False)
    directory = tmp_path / "ens"
    deadline = time.monotonic() + 120
    while len(list(directory.glob("chunk-*.npz"))) < 3:
        assert time.monotonic() < deadline and proc.poll() is None, proc.stderr.read() if proc.poll() else "slow"
        time.sleep(0.05)
    proc.kill()
    proc.wait()
    kept = {path.name: path.stat().st_mtime_ns for path in directory.glob("chunk-*.npz")}
    assert 3 <= len(kept) < 40 and not (directory / "ensemble.json").exists()
    files = run_ensemble(directory)
    assert all((directory / name).stat().st_mtime_ns == mtime for name, mtime in kept.items())
    assert files.solved == 40 and len(files) == 40
    values = files.solution()
    np.testing.assert_allclose(values["x"], np.exp(-np.outer(K, values.t)), rtol=1e-8)


def test_two_writers_of_one_directory(tmp_path):
    """While one ensemble writes a directory, a second (here, in this process) is refused with
    the holder named; the first finishes whole, and the lock is gone after it."""
    proc = child(SLOW_CHUNKS.format(pause=0.1) + "run_ensemble()\nprint('done')", tmp_path, wait=False)
    lock = tmp_path / "ens" / ".daemodel-lock"
    deadline = time.monotonic() + 120
    while not lock.exists() or not lock.read_text():
        assert time.monotonic() < deadline and proc.poll() is None
        time.sleep(0.02)
    with pytest.raises(
        InvalidOptionError, match=rf"write_to .*ens is being written by another run \(process {proc.pid} on "
    ):
        run_ensemble(tmp_path / "ens")
    out, err = proc.communicate(timeout=120)
    assert out.strip().endswith("done"), err[-2000:]
    assert not lock.exists()
    assert dm.EnsembleFiles.load(tmp_path / "ens", decay).solved == 40


# ---- links and names that would leave the directory -----------------------------------------------
def test_a_planted_link_is_replaced_never_followed(tmp_path):
    outside = tmp_path / "outside.txt"
    outside.write_text("precious")
    work = tmp_path / "work"
    work.mkdir()
    (work / "solution.npz").symlink_to(outside)
    for pid in range(os.getpid() - 2, os.getpid() + 3):  # the old predictable write-check names
        (work / f".daemodel-write-check-{pid}").symlink_to(outside)
    sol = dm.solve(decay, (0.0, 1.0), h=0.1)
    sol.save(work / "solution.npz")
    files = dm.ensemble(decay, (0.0, 1.0), h=0.1, parameters={"k": [1.0, 2.0]}, write_to=work)
    assert outside.read_text() == "precious"
    assert not (work / "solution.npz").is_symlink() and dm.Solution.load(work / "solution.npz", decay).t[-1] == 1.0
    # a chunk file replaced by a link to a file outside is not read
    (work / "chunk-000000000000.npz").unlink()
    (work / "chunk-000000000000.npz").symlink_to(tmp_path / "work" / "solution.npz")
    with pytest.raises(SolutionFileError, match=r"1 of the ensemble's 1 chunk files are missing"):
        dm.EnsembleFiles.load(files.directory, decay)
    # a lock file planted as a link
    (tmp_path / "locked").mkdir()
    (tmp_path / "locked" / ".daemodel-lock").symlink_to(outside)
    with pytest.raises(InvalidOptionError, match=r"write_to .*locked cannot be locked: .*\.daemodel-lock"):
        dm.ensemble(decay, (0.0, 1.0), h=0.1, write_to=tmp_path / "locked")
    assert outside.read_text() == "precious"


@pytest.mark.parametrize("name", ["../evil", "/tmp/evil", "..", ".hidden", "a/b", "", "x" * 201, 7])
def test_a_comparisons_model_name_cannot_name_a_path(saved, tmp_path, name):
    path = saved["comparison"][0]
    payload = json.loads(path.read_text())
    payload["model"] = name
    edited = tmp_path / "edited.json"
    edited.write_text(json.dumps(payload))
    with pytest.raises(ComparisonError, match=r"edited.json: field 'model' = .* cannot name a file"):
        dm.Comparison.load(edited)
    forged = dataclasses.replace(dm.Comparison.load(path), model=name)
    with pytest.raises(ComparisonError, match=r"the comparison's model name = .* cannot name a file"):
        forged.save(tmp_path / "out")
    assert not [p for p in tmp_path.parent.iterdir() if p.name == "evil"]


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda m: m["files"][0].update(file="../chunk-000000000000.npz"), r"field 'files\[0\].file' is '\.\./chunk"),
        (lambda m: m["files"][0].update(file="/etc/passwd"), r"field 'files\[0\].file' is '/etc/passwd'"),
        (lambda m: m.update(total=10**8), r"field 'total' is 100000000, but the chunks hold 3 solved samples"),
        (lambda m: m["files"][0].update(solved=10**8), r"field 'files\[0\].solved' is 100000000, not a whole number"),
        (lambda m: m["files"][1].update(offset=1), r"field 'files\[1\].offset' is 1, not a whole number from 2"),
        (lambda m: m.update(total=True), r"field 'total' is True"),
        (lambda m: m["failures"].append({"index": 0}), r"field 'failures\[0\]' is not an index, an error and a mess"),
    ],
)
def test_a_manifest_edited_to_leave_the_directory_or_inflate_is_refused(saved, tmp_path, edit, message):
    source = saved["manifest"][0].parent
    for path in source.iterdir():
        (tmp_path / path.name).write_bytes(path.read_bytes())
    manifest = json.loads((tmp_path / "ensemble.json").read_text())
    edit(manifest)
    (tmp_path / "ensemble.json").write_text(json.dumps(manifest))
    with pytest.raises(SolutionFileError, match=message):
        dm.EnsembleFiles.load(tmp_path, decay)


def test_a_deeply_nested_json_is_refused(tmp_path):
    (tmp_path / "ensemble.json").write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(SolutionFileError, match=r"is not a daemodel ensemble manifest \(RecursionError: "):
        dm.EnsembleFiles.load(tmp_path, decay)
    (tmp_path / "deep.json").write_text('{"runs": ' + "[" * 40 + "]" * 40 + "}")
    with pytest.raises(ComparisonError, match=r"deep.json is not a comparison .*: it nests deeper than 32 levels"):
        dm.Comparison.load(tmp_path / "deep.json")


# ---- loaders that check every field ----------------------------------------------------------------
def _forge(tmp_path, saved, **changes) -> Path:
    """A copy of the saved solution with some arrays or meta fields replaced."""
    with np.load(saved["solution"][0], allow_pickle=False) as data:
        arrays = {key: data[key] for key in data.files}
    meta = json.loads(str(arrays["meta"]))
    for key, value in changes.items():
        if key in arrays:
            arrays[key] = value
        else:
            meta[key] = value
    arrays["meta"] = np.array(json.dumps(meta))
    path = tmp_path / "forged.npz"
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"names": ["x", "x"]}, r"field 'names' is \['x', 'x'\]; the model's variables are 'x'$"),
        ({"names": []}, r"field 'names' is \[\]; the model's variables are 'x'$"),
        ({"t": np.array([0.0, np.nan, 1.0])}, r"field 't' is not a non-empty, finite, increasing"),
        ({"t": np.array([0.0, 0.5, 0.4])}, r"field 't' is not a non-empty, finite, increasing"),
        ({"t": np.linspace(0, 1, 5)}, r"field 'values' has shape \(2, 11, 1\); 2 samples, 5 times and 1 variables"),
        ({"parameters": np.ones((2, 3))}, r"field 'parameters' has shape \(2, 3\)"),
        ({"batched": False}, r"an unbatched solution has one sample"),
        ({"batched": "yes"}, r"field 'batched' is a str, not a bool"),
        ({"solve_time": True}, r"field 'solve_time' is a bool, not a number"),
        ({"values": np.ones((2, 11, 1), dtype=complex)}, r"field 'values' is an array of complex128"),
        ({"t": np.ones((2, 2))}, r"field 't' is an array of float64 with 2 axes; expected 1"),
    ],
)
def test_a_solution_file_with_a_bad_field_names_it(saved, tmp_path, changes, message):
    path = _forge(tmp_path, saved, **changes)
    with pytest.raises(SolutionFileError, match=message):
        dm.Solution.load(path, decay)


def test_a_solution_file_whose_names_are_long_is_refused_in_a_short_message(saved, tmp_path):
    """10^5 forged names: the message quotes their start, not all of them (it printed every one)."""
    path = _forge(tmp_path, saved, names=[f"v{k}" for k in range(100_000)])
    with pytest.raises(
        SolutionFileError, match=r"field 'names' is \['v0', 'v1', .*\.\.\.; the model's variables are 'x'$"
    ) as raised:
        dm.Solution.load(path, decay)
    assert len(str(raised.value)) < 400


def test_messages_list_the_first_items_and_count_the_rest():
    from daemodel.messages import listed

    assert listed(["a", "b"]) == "'a', 'b'"
    assert listed([f"u[{k}]" for k in range(12)], most=2) == "'u[0]', 'u[1]' and 10 more"
    assert listed([]) == ""


def test_a_solution_file_with_an_object_array_or_an_extra_member_is_refused_unread(saved, tmp_path):
    """An object array would need a pickle: refused from its header.  A member daemodel does not
    write: refused by name."""
    path = tmp_path / "objects.npz"
    arrays = dict(np.load(saved["solution"][0], allow_pickle=False))
    with zipfile.ZipFile(path, "w") as archive:
        for key, value in arrays.items():
            with archive.open(f"{key}.npy", "w") as member:
                if key == "values":
                    np.lib.format.write_array(member, np.array([None, print], dtype=object), allow_pickle=True)
                else:
                    np.lib.format.write_array(member, value)
    with pytest.raises(SolutionFileError, match=r"field 'values' is an array of object with 1 axes"):
        dm.Solution.load(path, decay)
    with zipfile.ZipFile(path, "a") as archive:
        archive.writestr("extra.npy", b"")
    with pytest.raises(SolutionFileError, match=r"holds a field 'extra' that it should not"):
        dm.Solution.load(path, decay)


def test_a_solution_file_missing_a_field_or_declaring_more_than_it_holds(saved, tmp_path):
    path = _forge(tmp_path, saved)
    arrays = dict(np.load(path, allow_pickle=False))
    del arrays["parameters"]
    np.savez(tmp_path / "short.npz", **arrays)
    with pytest.raises(SolutionFileError, match=r"short.npz lacks the field 'parameters'"):
        dm.Solution.load(tmp_path / "short.npz", decay)
    meta = json.loads(str(arrays["meta"]))
    del meta["fingerprint"]
    arrays["meta"], arrays["parameters"] = np.array(json.dumps(meta)), np.array([[1.0], [2.0]])
    np.savez(tmp_path / "nofp.npz", **arrays)
    with pytest.raises(SolutionFileError, match=r"nofp.npz lacks the field 'fingerprint'"):
        dm.Solution.load(tmp_path / "nofp.npz", decay)
    # a header that declares a larger array than the member holds (a consistent archive otherwise)
    arrays = dict(np.load(saved["solution"][0], allow_pickle=False))
    with zipfile.ZipFile(tmp_path / "liar.npz", "w") as archive:
        for key, value in arrays.items():
            with archive.open(f"{key}.npy", "w") as member:
                if key == "values":
                    np.lib.format.write_array_header_1_0(
                        member, {"descr": "<f8", "fortran_order": False, "shape": (9, 11, 1)}
                    )
                    member.write(value.tobytes())
                else:
                    np.lib.format.write_array(member, value)
    with pytest.raises(
        SolutionFileError, match=r"field 'values' declares shape \(9, 11, 1\) \(792 bytes\) in 304 bytes"
    ):
        dm.Solution.load(tmp_path / "liar.npz", decay)


# ---- bombs, checked under a memory limit -------------------------------------------------------------
def test_a_zip_bomb_and_an_inflated_manifest_are_refused_before_allocating(saved, tmp_path):
    """In a child whose address space is capped 400 MB above what it holds after import: a
    solution file of 640 MB of zeros deflated to under 1 MB, and a manifest whose chunk claims
    10^10 samples, are refused by name, not by a MemoryError."""
    bomb = tmp_path / "bomb.npz"
    arrays = dict(np.load(saved["solution"][0], allow_pickle=False))
    with zipfile.ZipFile(bomb, "w") as archive:  # stored, as daemodel writes, but for the values
        for key in ("t", "parameters", "meta"):
            with archive.open(f"{key}.npy", "w") as member:
                np.lib.format.write_array(member, arrays[key])
        B, T = 2, 40_000_000  # 640 MB of float64 values
        archive.compression = zipfile.ZIP_DEFLATED
        with archive.open("values.npy", "w", force_zip64=True) as member:
            header = {"descr": "<f8", "fortran_order": False, "shape": (B, T, 1)}
            np.lib.format.write_array_header_2_0(member, header)
            zeros = bytes(1 << 24)
            for _ in range(B * T * 8 // len(zeros)):
                member.write(zeros)
    assert bomb.stat().st_size < 5 << 20
    inflated = tmp_path / "inflated"
    inflated.mkdir()
    for path in saved["manifest"][0].parent.iterdir():
        (inflated / path.name).write_bytes(path.read_bytes())
    manifest = json.loads((inflated / "ensemble.json").read_text())
    manifest["total"], manifest["files"] = 10**10, [{**manifest["files"][0], "size": 10**10, "solved": 10**10}]
    (inflated / "ensemble.json").write_text(json.dumps(manifest))
    out = child(
        """
        import resource
        from daemodel.errors import ResourceLimitError, SolutionFileError
        size = int(open("/proc/self/statm").read().split()[0]) * resource.getpagesize()
        resource.setrlimit(resource.RLIMIT_AS, (size + (400 << 20), resource.RLIM_INFINITY))
        try:
            dm.Solution.load("bomb.npz", decay)
        except SolutionFileError as error:
            print("bomb:", error)
        files = dm.EnsembleFiles.load("inflated", decay)
        try:
            files.solution()
        except ResourceLimitError as error:
            print("solution:", error)
        try:
            list(files)
        except SolutionFileError as error:
            print("chunks:", error)
        """,
        tmp_path,
    )
    assert "bomb: bomb.npz: member 'values.npy' is compressed" in out
    assert "solution: EnsembleFiles.solution of 10000000000 samples of 11 times and 1 variables would need 820 GiB" in (
        out
    )
    assert "chunks: inflated/chunk-000000000000.npz holds 2 samples, not the 10000000000" in out


def test_a_network_file_that_is_a_bomb_is_refused(saved, tmp_path):
    path = tmp_path / "bomb.pt"
    with zipfile.ZipFile(saved["networks"][0]) as source, zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as bomb:
        for member in source.infolist():
            bomb.writestr(member.filename, source.read(member))
    with pytest.raises(NetworkFileError, match=r"bomb.pt: member '.*' is compressed"):
        dm.Surrogate.load(path, PENDULUM.model())


# ---- ensembles: foreign chunks, adaptive radau ----------------------------------------------------------
def test_a_foreign_chunk_is_refused_on_resume_and_on_load(tmp_path):
    k = [1.0, 2.0, 3.0]
    ours = dm.ensemble(decay, (0.0, 1.0), h=0.1, parameters={"k": k}, chunk=2, write_to=tmp_path / "ours")
    other = dm.ensemble(decay, (0.0, 1.0), h=0.1, parameters={"k": [5.0, 6.0, 7.0]}, chunk=2, write_to=tmp_path / "b")
    foreign = (other.directory / "chunk-000000000002.npz").read_bytes()
    # on load: the manifest's own chunk replaced by another run's
    (ours.directory / "chunk-000000000002.npz").write_bytes(foreign)
    files = dm.EnsembleFiles.load(ours.directory, decay)
    with pytest.raises(SolutionFileError, match=r"chunk-000000000002.npz is a chunk of another ensemble run"):
        files.solution([2])
    # on resume: an interrupted directory holding another run's chunk
    (tmp_path / "resume").mkdir()
    (tmp_path / "resume" / "chunk-000000000002.npz").write_bytes(foreign)
    with pytest.raises(InvalidOptionError, match=r"chunk-000000000002.npz is not a chunk of this ensemble"):
        dm.ensemble(decay, (0.0, 1.0), h=0.1, parameters={"k": k}, chunk=2, write_to=tmp_path / "resume")
    (tmp_path / "resume" / "chunk-000000000007.npz").write_bytes(foreign)
    (tmp_path / "resume" / "chunk-000000000002.npz").unlink()
    with pytest.raises(InvalidOptionError, match=r"chunk-000000000007.npz is not one of this ensemble's chunk files"):
        dm.ensemble(decay, (0.0, 1.0), h=0.1, parameters={"k": k}, chunk=2, write_to=tmp_path / "resume")
    # the finished directory of the same call: returned as it is, nothing solved again
    again = dm.ensemble(decay, (0.0, 1.0), h=0.1, parameters={"k": [5.0, 6.0, 7.0]}, chunk=2, write_to=tmp_path / "b")
    assert again.seconds == other.seconds and again.run == other.run


def test_adaptive_radau_in_an_ensemble_matches_single_solves(tmp_path):
    """k = 1, 1.1 and 1000 in chunks of one and two: every sample on t_eval equals its own
    solve and the exact exp(-k t) to 1e-8; without t_eval the ensemble is refused, by name."""
    k = np.array([1.0, 1.1, 1000.0])
    t_eval = np.linspace(0.0, 1.0, 21)
    options = {"rtol": 1e-10, "atol": 1e-12, "t_eval": t_eval}
    single = np.stack([dm.solve(decay, (0.0, 1.0), parameters={"k": v}, **options)["x"] for v in k])
    for chunk in (1, 2):
        memory = dm.ensemble(decay, (0.0, 1.0), parameters={"k": k}, chunk=chunk, **options)
        files = dm.ensemble(
            decay, (0.0, 1.0), parameters={"k": k}, chunk=chunk, write_to=tmp_path / f"c{chunk}", **options
        )
        for values in (memory["x"], files.solution()["x"]):
            np.testing.assert_allclose(values, single, rtol=0, atol=1e-8)
            np.testing.assert_allclose(values, np.exp(-np.outer(k, t_eval)), rtol=0, atol=1e-8)
    with pytest.raises(InvalidOptionError, match=r"radau with adaptive steps and no t_eval reports each batch on the"):
        dm.ensemble(decay, (0.0, 1.0), parameters={"k": k}, chunk=2, rtol=1e-8)
    assert dm.ensemble(decay, (0.0, 1.0), rtol=1e-8).batch_size == 1  # one sample: its own steps


# ---- small things ------------------------------------------------------------------------------------
def test_written_files_get_the_usual_permissions_and_no_partial_file(tmp_path):
    sol = dm.solve(decay, (0.0, 1.0), h=0.1)
    path = sol.save(tmp_path / "s.npz")
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask
    os.chmod(path, 0o600)
    sol.save(path)  # a file written over keeps its mode
    assert path.stat().st_mode & 0o777 == 0o600
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.npz"]


def test_a_write_that_fails_for_another_reason_leaves_nothing(tmp_path, monkeypatch):
    """An exception inside the writer (here, matplotlib refusing) removes the temporary file."""
    sol = dm.solve(decay, (0.0, 1.0), h=0.1)
    with pytest.raises(InvalidOptionError, match=r"plot path = '.*plot.xyz': matplotlib writes no '.xyz' files"):
        sol.plot(tmp_path / "plot.xyz")
    from daemodel import files

    def broken(handle):
        handle.write(b"half")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        files.atomic_write(tmp_path / "x.bin", broken)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(FileWriteError, match=r"nowhere/x.bin could not be written"):
        files.atomic_write(tmp_path / "nowhere" / "x.bin", broken)


def test_loading_an_entire_ensemble_is_bounded(saved, monkeypatch):
    files = dm.EnsembleFiles.load(saved["manifest"][0].parent, decay)
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "100")
    with pytest.raises(ResourceLimitError, match=r"of 3 samples of 11 times and 1 variables would need 2.46e-07 GiB"):
        files.solution()  # refused from the first chunk's header, before any values are read
    monkeypatch.delenv("DAEMODEL_MEMORY_LIMIT")
    assert files.solution()["x"].shape == (3, 11)


# ---- memory bounds before allocation ---------------------------------------------------------------
def test_a_solve_whose_outputs_would_not_fit_is_refused_before_it_starts():
    with pytest.raises(
        ResourceLimitError,
        match=r"radau on 1000000 sample\(s\) of 1 unknowns would need 74.6 GiB \(Newton matrices 0.0522 GiB, "
        r"outputs 74.5 GiB\), more than the .* GiB allowed \(set DAEMODEL_MEMORY_LIMIT",
    ):
        dm.solve(decay, (0.0, 1.0), h=1e-4, parameters={"k": np.ones(10**6)}, dense_output=False)
    with pytest.raises(  # (the dense output: the start and s = 3 stages of every step)
        ResourceLimitError,
        match=r"would need 298 GiB \(Newton matrices 0.0522 GiB, outputs with the dense output "
        r"\(dense_output=False keeps the step ends only\) 298 GiB\)",
    ):
        dm.solve(decay, (0.0, 1.0), h=1e-4, parameters={"k": np.ones(10**6)})


def test_adaptive_steps_stop_at_the_memory_limit(monkeypatch):
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "20K")
    k = {"k": np.linspace(1.0, 50.0, 100)}
    with pytest.raises(ResourceLimitError, match=r"radau: at t = .*, the 15 steps' outputs of 100 sample\(s\) reach"):
        dm.solve(decay, (0.0, 100.0), rtol=1e-10, parameters=k, dense_output=False, stages=5)
    # (with the dense output, each step keeps its start and stages: 6 values where its end is 1)
    with pytest.raises(ResourceLimitError, match=r"radau: at t = .*, the 3 steps' outputs of 100 sample\(s\) reach"):
        dm.solve(decay, (0.0, 100.0), rtol=1e-10, parameters=k, stages=5)
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "lots")
    with pytest.raises(InvalidOptionError, match=r"DAEMODEL_MEMORY_LIMIT = 'lots' is not a memory size"):
        dm.solve(decay, (0.0, 1.0), h=0.1)


def test_an_ensemble_too_big_for_memory_is_stopped_before_its_first_chunk(monkeypatch, tmp_path):
    """2000 samples of 101 times need 1.6 MB; with 200 KB allowed the in-memory ensemble is refused
    before its first chunk, and write_to= (one chunk of 81 KB in memory at a time) runs."""
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "200K")
    k = {"k": np.linspace(1.0, 2.0, 2000)}
    with pytest.raises(ResourceLimitError, match=r"ensemble of 2000 samples kept in memory would need 0.00151 GiB"):
        dm.ensemble(decay, (0.0, 1.0), h=0.01, parameters=k, chunk=100)
    files = dm.ensemble(decay, (0.0, 1.0), h=0.01, parameters=k, chunk=100, write_to=tmp_path)
    assert files.solved == 2000
    part = next(iter(files))
    np.testing.assert_allclose(part["x"][:, -1], np.exp(-part.parameters[:, 0]), rtol=1e-9)


# ---- Ray: loopback, time limits -------------------------------------------------------------------------
@pytest.mark.slow  # a Ray cluster of its own: about 80 s
def test_a_ray_cluster_daemodel_starts_listens_on_loopback_and_stops_a_task_past_its_limit(tmp_path):
    pytest.importorskip("ray")
    out = child(
        """
        import time
        from daemodel.executors import connect, run_tasks
        from daemodel.errors import TimeLimitError
        import subprocess
        ray = connect(1, None)
        print("nodes:", sorted({node["NodeManagerAddress"] for node in ray.nodes()}))
        listening = subprocess.run(["ss", "-Hltnp"], capture_output=True, text=True).stdout.splitlines()
        ours = [line.split()[3] for line in listening if any(n in line for n in ("gcs_server", "raylet", "ray::"))]
        print("listening:", len(ours), sorted({a.rsplit(":", 1)[0].strip("[]").removeprefix("::ffff:") for a in ours}))
        def sleepy(shared, seconds):
            time.sleep(seconds)
            return seconds
        print("quick:", run_tasks(sleepy, None, [(0.1,)], executor="ray", label="nap", task_timeout=30))
        began = time.perf_counter()
        try:
            run_tasks(sleepy, None, [(60,)], executor="ray", label="nap", task_timeout=2)
        except TimeLimitError as error:
            print("stopped after %.0f s:" % (time.perf_counter() - began), error)
        """,
        tmp_path,
        timeout=240,
    )
    assert "nodes: ['127.0.0.1']" in out
    count, hosts = out.split("listening: ")[1].split("\n")[0].split(" ", 1)
    assert int(count) >= 3 and hosts == "['127.0.0.1']", out  # the GCS, the raylet and the workers
    assert "quick: [0.1]" in out
    assert "nap: task 0 ran past its time limit of 2 s (task_timeout) and was stopped" in out
    assert int(out.split("stopped after ")[1].split(" s")[0]) < 30


def test_task_timeout_errors(blowup):
    with pytest.raises(InvalidOptionError, match=r"task_timeout must be a positive number of seconds or None; got 0"):
        dm.ensemble(blowup, (0.0, 1.0), h=0.1, task_timeout=0)


@pytest.mark.parametrize(("method", "options"), [("reference", {}), ("casadi-idas", {}), ("casadi-collocation", {})])
def test_every_method_refuses_outputs_that_would_not_fit(method, options):
    t_eval = np.linspace(0.0, 1.0, 10**6)
    with pytest.raises(ResourceLimitError, match=rf"{method} on 10000 sample\(s\) of 1 unknowns would need 74.5 GiB"):
        dm.solve(decay, (0.0, 1.0), method=method, parameters={"k": np.ones(10**4)}, t_eval=t_eval, **options)


def test_a_solution_file_larger_than_the_memory_allowed_is_refused_unread(saved, monkeypatch):
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "1K")
    refused = r"solution.npz holds [\d.]+ KiB, more than the 1 KiB allowed \(set DAEMODEL_MEMORY_LIMIT"
    with pytest.raises(SolutionFileError, match=refused):
        dm.Solution.load(saved["solution"][0], decay)


# ---- what a review of the first version found -------------------------------------------------------
def test_a_fifo_in_place_of_a_file_is_refused_without_hanging(tmp_path):
    os.mkfifo(tmp_path / "solution.npz")
    with pytest.raises(SolutionFileError, match=r"solution.npz \(path\) is not a plain file"):
        dm.Solution.load(tmp_path / "solution.npz", decay)
    os.mkfifo(tmp_path / "ensemble.json")
    with pytest.raises(SolutionFileError, match=r"ensemble.json \(path\) is not a plain file"):
        dm.EnsembleFiles.load(tmp_path, decay)
    (tmp_path / "ensemble.json").unlink()
    os.mkfifo(tmp_path / "chunk-000000000000.npz")
    with pytest.raises(InvalidOptionError, match=r"chunk-000000000000.npz is not one of this ensemble's chunk files"):
        dm.ensemble(decay, (0.0, 1.0), h=0.1, parameters={"k": [1.0, 2.0]}, write_to=tmp_path)


def test_a_member_named_without_its_suffix_is_refused_by_name(saved, tmp_path):
    arrays = dict(np.load(saved["solution"][0], allow_pickle=False))
    with zipfile.ZipFile(tmp_path / "bare.npz", "w") as archive:
        for key, value in arrays.items():
            with archive.open(key if key == "t" else f"{key}.npy", "w") as member:
                np.lib.format.write_array(member, value)
    with pytest.raises(SolutionFileError, match=r"bare.npz lacks the field 't'"):
        dm.Solution.load(tmp_path / "bare.npz", decay)


def _chunk_with(tmp_path, saved, **stats) -> Path:
    """A copy of the saved ensemble whose first chunk's stats are changed."""
    for path in saved["manifest"][0].parent.iterdir():
        (tmp_path / path.name).write_bytes(path.read_bytes())
    chunk = tmp_path / "chunk-000000000000.npz"
    arrays = dict(np.load(chunk, allow_pickle=False))
    meta = json.loads(str(arrays["meta"]))
    meta["stats"].update(stats)
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez(chunk, **arrays)
    return tmp_path


@pytest.mark.parametrize("samples", [["a", "b"], [10**30, 1], {"a": 1}, [0, 0], [[0], [1]], [0]])
def test_a_chunk_with_forged_sample_indices_is_refused(saved, tmp_path, samples):
    directory = _chunk_with(tmp_path, saved, samples=samples)
    files = dm.EnsembleFiles.load(directory, decay)
    with pytest.raises(SolutionFileError, match=r"field 'stats.samples' is not 2 distinct sample indices, one a row"):
        files.solution()


def test_a_manifest_with_forged_fields_or_a_gap_is_refused(saved, tmp_path):
    for path in saved["manifest"][0].parent.iterdir():
        (tmp_path / path.name).write_bytes(path.read_bytes())
    original = json.loads((tmp_path / "ensemble.json").read_text())
    cases = [
        ({"seconds": "abc"}, r"field 'seconds' is 'abc', not a number"),
        ({"status": None}, r"field 'status' is not a string"),
        ({"seconds": float("nan")}, r"ensemble.json is not a daemodel ensemble manifest \(ValueError: NaN is not a"),
        # samples 0 and 1 marked failed while their chunk says they were solved
        (
            {
                "failures": [{"index": i, "error": "E", "message": "m"} for i in (0, 1)],
                "files": original["files"][:1],
                "total": 4,
            },
            r"field 'files\[0\].solved' is 2, but 2 of the chunk's 2 failed",
        ),
        (
            {"failures": [{"index": 0, "error": "E", "message": "m"}], "total": 4},
            r"field 'files\[0\].solved' is 2, but 1 of the chunk's 2 failed",
        ),
        ({"format": "daemodel-ensemble/1"}, r"is a daemodel ensemble of format 'daemodel-ensemble/1', whose chunks"),
    ]
    for change, message in cases:
        text = json.dumps({**original, **change}, allow_nan=True)
        (tmp_path / "ensemble.json").write_text(text)
        with pytest.raises(SolutionFileError, match=message):
            dm.EnsembleFiles.load(tmp_path, decay)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("t_span", ["a", "b"], r"field 't_span' is not a number"),
        ("t_span", [], r"field 't_span' is not a pair of numbers"),
        ("t_span", [1.0, 0.0], r"field 't_span' is not a finite, increasing pair"),
        ("states", [], r"field 'states' is not a non-empty list"),
        ("states", [1], r"field 'states' is not a list of strings"),
        ("runs", {}, r"field 'runs' is not a list"),
    ],
)
def test_a_comparison_with_forged_fields_is_refused_on_load(saved, tmp_path, field, value, message):
    payload = json.loads(saved["comparison"][0].read_text())
    payload[field] = value
    (tmp_path / "c.json").write_text(json.dumps(payload))
    with pytest.raises(ComparisonError, match=message):
        dm.Comparison.load(tmp_path / "c.json")


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda r: r.update(errors={}), r"field 'runs\[0\].errors' is not an entry for every variable"),
        (lambda r: r["errors"]["y1"].update(max="big"), r"field 'runs\[0\].errors.y1.max' is not a number or null"),
        (lambda r: r.update(method=5), r"field 'runs\[0\].method' is not a string"),
        (lambda r: r.update(step=[3]), r"field 'runs\[0\].step' is not empty or a pair"),
    ],
)
def test_a_comparison_run_with_forged_fields_is_refused_on_load(saved, tmp_path, edit, message):
    payload = json.loads(saved["comparison"][0].read_text())
    edit(payload["runs"][0])
    (tmp_path / "c.json").write_text(json.dumps(payload))
    with pytest.raises(ComparisonError, match=message):
        dm.Comparison.load(tmp_path / "c.json")


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("inputs", 5, r"field 'inputs' is not a list of distinct parameters of the model \(m, lam\)"),
        ("inputs", [["m"]], r"field 'inputs' is not a list of distinct parameters"),
        ("config", [1], r"field 'config' is not a table of settings"),
        ("config", {"no_such_setting": 1}, r"records settings that are not valid"),
        ("grid", ["a"], r"field 'grid' is not an increasing list of at least two finite times"),
        ("grid", 1.0, r"field 'grid' is not an increasing list"),
        ("parameter_values", [], r"field 'parameter_values' is not 2 numbers, one a parameter"),
        ("networks", 5, r"field 'networks' is not a list with a table a segment"),
    ],
)
def test_a_network_file_with_forged_fields_is_refused(saved, tmp_path, key, value, message):
    import torch

    payload = torch.load(saved["networks"][0], weights_only=True)
    payload[key] = value
    torch.save(payload, tmp_path / "forged.pt")
    with pytest.raises(NetworkFileError, match=message):
        dm.Surrogate.load(tmp_path / "forged.pt", PENDULUM.model())


def test_a_planted_link_does_not_lend_its_targets_mode(tmp_path):
    victim = tmp_path / "victim"
    victim.write_text("x")
    os.chmod(victim, 0o777)
    (tmp_path / "out.npz").symlink_to(victim)
    path = dm.solve(decay, (0.0, 1.0), h=0.1).save(tmp_path / "out.npz")
    umask = os.umask(0)
    os.umask(umask)
    assert not path.is_symlink() and path.stat().st_mode & 0o777 == 0o666 & ~umask


def test_a_time_limit_ends_an_ensemble_chunk_instead_of_splitting_it():
    """The limit is not a failing sample: the chunk is not bisected and solved again without it."""
    from daemodel.errors import TimeLimitError
    from daemodel.executors import _time_limit
    from daemodel.solving.ensemble import solve_chunk

    batch = {"parameters": np.linspace(1.0, 2.0, 64)[:, None], "y0": np.ones((64, 1))}
    began = time.perf_counter()
    with pytest.raises(TimeLimitError, match=r"chunks: task 3 ran past its time limit of 0.5 s"):
        with _time_limit(0.5, "chunks", 3):
            solve_chunk((decay, (0.0, 50.0), "radau", {"h": 1e-3}, None), 0, batch)
    assert time.perf_counter() - began < 5


def test_a_lock_whose_holder_cannot_be_written_is_released(tmp_path, monkeypatch):
    from daemodel.files import DirectoryLock

    def full(*_):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "write", full)
    with pytest.raises(FileWriteError, match=r"\.daemodel-lock could not be written: No space left on device"):
        DirectoryLock(tmp_path, "write_to").acquire()
    monkeypatch.undo()
    with DirectoryLock(tmp_path, "write_to"):  # not held any more
        pass


def test_a_resumed_ensemble_counts_the_failures_it_kept(blowup, tmp_path):
    k = {"k": [0.1, 5.0, 0.2, 6.0]}
    dm.ensemble(blowup, (0.0, 1.0), h=0.05, parameters=k, chunk=2, write_to=tmp_path)
    (tmp_path / "ensemble.json").unlink()
    (tmp_path / "chunk-000000000002.npz").unlink()
    with pytest.raises(dm.errors.ConvergenceError, match=r"more than max_failures=1 samples failed \(2 found"):
        dm.ensemble(blowup, (0.0, 1.0), h=0.05, parameters=k, chunk=2, write_to=tmp_path, max_failures=1)


def test_a_pinn_solve_whose_outputs_would_not_fit_is_refused_before_training(monkeypatch):
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "1K")
    with pytest.raises(ResourceLimitError, match=r"pinn on 200 sample\(s\) of 1 unknowns would need"):
        dm.solve(decay, (0.0, 1.0), method="pinn", parameters={"k": np.ones(200)}, config=TINY)


@pytest.mark.parametrize("argument", [3, None, {"path": "x.npz"}, b"x.npz"], ids=["int", "None", "dict", "bytes"])
def test_a_loader_given_no_path_names_the_argument_and_what_it_takes(argument):
    """Path(3) or Path(None) raised a bare TypeError that named neither the loader nor the argument."""
    from daemodel.solving.surrogates import Surrogate

    model = PENDULUM.model()
    got = r" path \(str or pathlib\.Path\); got " + re.escape(repr(argument)) + rf" \({type(argument).__name__}\)$"
    loaders = [
        (SolutionFileError, r"^Solution\.load: path must be a file", lambda: dm.Solution.load(argument, model)),
        (
            SolutionFileError,
            r"^EnsembleFiles\.load: directory must be a directory",
            lambda: dm.EnsembleFiles.load(argument, model),
        ),
        (NetworkFileError, r"^Surrogate\.load: path must be a file", lambda: Surrogate.load(argument, model)),
        (ComparisonError, r"^Comparison\.load: path must be a file", lambda: dm.Comparison.load(argument)),
    ]
    for error, message, load in loaders:
        with pytest.raises(error, match=message + got):
            load()


# ---- the memory allowance: RAM, cgroup, address space ------------------------------------------------------------
def test_the_memory_allowance_honours_the_cgroup_limit(monkeypatch, tmp_path):
    """A process in a control group of 1 GiB may take half of that, not half of the machine's RAM (before:
    the machine's RAM alone); cgroup v2 (the group /proc/self/cgroup names) and v1 alike."""
    from daemodel import files

    monkeypatch.delenv("DAEMODEL_MEMORY_LIMIT", raising=False)
    table, root = tmp_path / "cgroup", tmp_path / "fs"
    (root / "jobs" / "one").mkdir(parents=True)
    (root / "jobs" / "one" / "memory.max").write_text("1073741824\n")
    table.write_text("0::/jobs/one\n")
    monkeypatch.setattr(files, "CGROUP_TABLE", table)
    monkeypatch.setattr(files, "CGROUP_ROOT", root)
    monkeypatch.setattr(files, "CGROUP_V1_LIMIT", tmp_path / "none" / "memory.limit_in_bytes")
    assert files.memory_available()["cgroup memory limit"] == 1 << 30
    assert files.memory_limit() == 1 << 29
    with pytest.raises(
        ResourceLimitError,
        match=r"ensemble of 1000 samples kept in memory would need 0\.745 GiB \(outputs of at least 100001 times x 1 "
        r"variables 0\.745 GiB\), more than the 0\.5 GiB allowed \(set DAEMODEL_MEMORY_LIMIT, e\.g\. '64G', to change "
        r"it; now 0\.5 of the cgroup memory limit \(1 GiB\)\)",
    ):
        dm.ensemble(decay, (0.0, 1.0), h=1e-5, parameters={"k": np.linspace(1, 2, 1000)})
    (root / "jobs" / "one" / "memory.max").write_text("max\n")  # v2 without a limit; v1 with one
    v1 = tmp_path / "v1" / "docker" / "abc" / "memory.limit_in_bytes"
    v1.parent.mkdir(parents=True)
    v1.write_text(str(3 << 29))
    table.write_text("4:memory:/docker/abc\n0::/jobs/one\n")
    monkeypatch.setattr(files, "CGROUP_V1_LIMIT", tmp_path / "v1" / "memory.limit_in_bytes")
    assert files.memory_limit() == 3 << 28
    v1.write_text("9223372036854771712")  # v1's way of saying none
    assert "cgroup memory limit" not in files.memory_available()


def test_the_cgroup_limit_is_read_once_while_its_files_are_unchanged(monkeypatch, tmp_path):
    """Every solve asks for the memory allowance: the cgroup's files are read once and kept until one of them
    changes or CGROUP_RECHECK seconds pass (before: read on every call, 7 % of the wheelset's solve)."""
    from daemodel import files

    monkeypatch.delenv("DAEMODEL_MEMORY_LIMIT", raising=False)
    table, root = tmp_path / "cgroup", tmp_path / "fs"
    (root / "jobs").mkdir(parents=True)
    (root / "jobs" / "memory.max").write_text("1073741824\n")
    table.write_text("0::/jobs\n")
    monkeypatch.setattr(files, "CGROUP_TABLE", table)
    monkeypatch.setattr(files, "CGROUP_ROOT", root)
    monkeypatch.setattr(files, "CGROUP_V1_LIMIT", tmp_path / "none" / "memory.limit_in_bytes")
    reads = []
    read_bytes = files._read_bytes
    monkeypatch.setattr(files, "_read_bytes", lambda path: reads.append(path) or read_bytes(path))
    assert files.memory_limit() == 1 << 29
    first = len(reads)
    assert first and [files.memory_limit() for _ in range(3)] == [1 << 29] * 3
    assert len(reads) == first
    (root / "jobs" / "memory.max").write_text("536870912\n")  # (a changed limit: seen at once)
    assert files.memory_limit() == 1 << 28
    assert len(reads) == 2 * first
    now = files.time.monotonic()  # (past CGROUP_RECHECK: read again, unchanged or not)
    monkeypatch.setattr(files.time, "monotonic", lambda: now + files.CGROUP_RECHECK)
    assert files.memory_limit() == 1 << 28
    assert len(reads) == 3 * first


def test_the_memory_allowance_honours_the_address_space_limit(tmp_path):
    """Under RLIMIT_AS, half the address space left (before: half the machine's RAM, so that a result
    the limit cannot hold was allocated until the allocator failed)."""
    out = child(
        """
        import resource
        from daemodel.files import memory_available, memory_limit
        size = int(open("/proc/self/statm").read().split()[0]) * resource.getpagesize()
        resource.setrlimit(resource.RLIMIT_AS, (size + (2 << 30), resource.RLIM_INFINITY))
        left = memory_available()["address space left under RLIMIT_AS"]
        print("left", left <= 2 << 30, left > 1 << 30, memory_limit() == left // 2)
        """,
        tmp_path,
    )
    assert "left True True True" in out
