"""Step, rejection, Jacobian and factorisation counts of Hairer's RADAU5 beside radau's (issue 26).

RADAU5 (Hairer & Wanner) is not part of daemodel: this script drives a locally built copy through
ctypes.  Build it from Assimulo's f2c translation (no Fortran compiler needed)::

    git clone https://github.com/modelon-community/Assimulo && cd Assimulo
    git checkout e85c74026e3e4599818e72c8bea722db6aef2359      # thirdparty/hairer/radau_decsol.c is C there
    cd thirdparty/hairer
    # edit radau_decsol.c near line 988: ``werr`` is allocated with n elements and indexed 1..n;
    # allocate n + 1 (e.g. calloc(*n + 1, sizeof(doublereal)))
    gcc -O2 -fPIC -std=gnu99 -w -c radau_decsol.c -o radau_decsol.o
    gcc -O2 -fPIC -std=gnu99 -I. -c /path/to/daemodel/benchmarks/radau5_f2c_stubs.c -o f2c_stubs.o
    gcc -shared -o libradau5.so radau_decsol.o f2c_stubs.o -lm

(``radau5_f2c_stubs.c`` supplies the few libf2c routines the translation calls.)  Then::

    python benchmarks/radau5_counts.py --lib /path/to/libradau5.so [--problems ...] [--tolerances ...] [--nmax N]

Each problem of :data:`PROBLEMS` is solved at rtol = atol in :data:`TOLERANCES` by RADAU5 (full
analytic Jacobian from casadi, mass matrix diag(1 for states, 0 for algebraics), NIND1-3 from
``CompiledDAE.algebraic_index`` with the algebraic variables ordered by index, all other settings
RADAU5's defaults: 7 Newton iterations, Gustafsson's controller, THET = 0.001, QUOT 1-1.2) and by
``dm.solve(..., rtol=tol, atol=tol, stages=3)`` (RADAU5's order).  RADAU5 integrates at an internal
tolerance 0.1 rtol^(2/3): it runs both at the same nominal tolerance ("same") and at
(10 tol)^1.5, whose internal tolerance is tol ("matched", the like-for-like count), and once
more at the same tolerance with THET = 0.1 (Hairer's advice where Jacobians are costly).  Index-3
models are given to both as daemodel solves them, reduced to index 2.  RADAU5's f sets
IPAR(1) = -1 where f is not finite (Assimulo's patch halves h then, as the Test Set's IERR = -1);
without it RADAU5 accepts a NaN step on Akzo-Nobel (its max(err, 1e-10) turns NaN into 1e-10).
Counts only: RADAU5's callbacks run in Python, so its times mean nothing and are not reported.

Writes ``<out>.json`` (the build, the call, every record with both codes' counts and the end
values' difference) and prints a markdown table.
"""

from __future__ import annotations

import argparse
import ctypes as C
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
PROBLEMS = ("pendulum", "robertson", "akzo-nobel", "car-axis", "transistor-amplifier", "squeezer", "ring-modulator")
TOLERANCES = (1e-4, 1e-6, 1e-8)
# RADAU5's defaults but for NMAX, its step budget (daemodel's radau gets the same below; --nmax sets it:
# the ring modulator takes RADAU5 65,000 steps at rtol 1e-6).
NMAX = 100_000

PI, PD = C.POINTER(C.c_int), C.POINTER(C.c_double)
FCN = C.CFUNCTYPE(C.c_int, PI, PD, PD, PD, PD, PI)
JAC = C.CFUNCTYPE(C.c_int, PI, PD, PD, PD, PI, PD, PI)
MAS = C.CFUNCTYPE(C.c_int, PI, PD, PI, PD, PI)
SOLOUT = C.CFUNCTYPE(C.c_int, PI, PD, PD, PD, PD, PD, PI, PI, PD, PI, PI)


def load(path: str):
    lib = C.CDLL(path)
    lib.radau5_c.restype = C.c_int
    lib.radau5_c.argtypes = [PI, FCN, PD, PD, PD, PD, PD, PD, PI, JAC, PI, PI, PI, MAS, PI, PI, PI]
    lib.radau5_c.argtypes += [SOLOUT, PI, PD, PI, PI, PI, PD, PI, PI]
    return lib


def functions(compiled):
    """casadi F(t, u, p) = [ode; alg] and dF/du, u = [x; z] with z ordered by index (RADAU5's order)."""
    import casadi

    dae = compiled.casadi_dae()
    index = list(compiled.algebraic_index)
    order = sorted(range(len(index)), key=lambda k: index[k])
    z = casadi.vertcat(*[dae["z"][k] for k in order]) if index else dae["z"]
    u = casadi.vertcat(dae["x"], z)
    F = casadi.vertcat(dae["ode"], dae["alg"])
    f = casadi.Function("F", [dae["t"], u, dae["p"]], [F])
    jac = casadi.Function("J", [dae["t"], u, dae["p"]], [casadi.densify(casadi.jacobian(F, u))])
    return f, jac, order, [sum(1 for k in index if k == j) for j in (1, 2, 3)]


def radau5(lib, compiled, t_span, tol, thet=0.0, nmax=NMAX):
    """RADAU5 on ``compiled``: IDID, its counters (IWORK(14..20)) and the end state."""
    f, jac, order, (index1, index2, index3) = functions(compiled)
    ns, m = len(compiled.state_names), len(compiled.algebraic_names)
    n = ns + m
    p = np.asarray(compiled.parameter_values, dtype=float)
    u = np.ascontiguousarray(np.concatenate([np.asarray(compiled.y0, float), np.asarray(compiled.z0, float)[order]]))
    guarded = [0]

    def fcn(_n, t, up, out, _rpar, ipar):
        value = np.asarray(f(t[0], np.ctypeslib.as_array(up, shape=(n,)), p)).ravel()
        np.ctypeslib.as_array(out, shape=(n,))[:] = value
        finite = bool(np.isfinite(value).all())
        guarded[0] += not finite
        ipar[0] = 0 if finite else -1  # Assimulo's patch: halve h (the Test Set's IERR = -1)
        return 0

    def dfy(_n, t, up, out, ld, _rpar, _ipar):
        values = np.asarray(jac(t[0], np.ctypeslib.as_array(up, shape=(n,)), p))
        np.ctypeslib.as_array(out, shape=(n, ld[0]))[:, :n] = values.T  # DFY(LDFY, N), column-major
        return 0

    def mass(_n, am, lmas, _rpar, _ipar):
        matrix = np.ctypeslib.as_array(am, shape=(n, lmas[0]))
        matrix[:] = 0.0
        matrix[np.arange(ns), np.arange(ns)] = 1.0
        return 0

    callbacks = FCN(fcn), JAC(dfy), MAS(mass), SOLOUT(lambda *args: 0)
    ints = {name: C.c_int(value) for name, value in (("n", n), ("itol", 0), ("ijac", 1), ("mljac", n), ("mujac", 0))}
    ints.update({name: C.c_int(value) for name, value in (("imas", 1), ("mlmas", n), ("mumas", 0), ("iout", 0))})
    t, t1, h = C.c_double(t_span[0]), C.c_double(t_span[1]), C.c_double(1e-6)
    rtol, atol = np.array([tol]), np.array([tol])
    lwork, liwork = n * (5 * n + 12) + 20, 3 * n + 20
    work = np.zeros(lwork)
    work[2] = thet  # WORK(3) = THET; 0: RADAU5's 0.001
    iwork = np.zeros(liwork, dtype=np.int32)
    iwork[1] = nmax  # IWORK(2) = NMAX (IWORK(1) is the Hessenberg switch)
    iwork[4:7] = ns + index1, index2, index3  # NIND1 (states and index-1 algebraics), NIND2, NIND3
    rpar, ipar, idid = np.zeros(1), np.zeros(1, dtype=np.int32), C.c_int(0)
    lib.radau5_c(
        C.byref(ints["n"]), callbacks[0], C.byref(t), u.ctypes.data_as(PD), C.byref(t1), C.byref(h),
        rtol.ctypes.data_as(PD), atol.ctypes.data_as(PD), C.byref(ints["itol"]), callbacks[1], C.byref(ints["ijac"]),
        C.byref(ints["mljac"]), C.byref(ints["mujac"]), callbacks[2], C.byref(ints["imas"]), C.byref(ints["mlmas"]),
        C.byref(ints["mumas"]), callbacks[3], C.byref(ints["iout"]), work.ctypes.data_as(PD),
        C.byref(C.c_int(lwork)), iwork.ctypes.data_as(PI), C.byref(C.c_int(liwork)), rpar.ctypes.data_as(PD),
        ipar.ctypes.data_as(PI), C.byref(idid),
    )  # fmt: skip
    names = ("NFCN", "NJAC", "NSTEP", "NACCPT", "NREJCT", "NDEC", "NSOL")
    stats = {name: int(iwork[13 + k]) for k, name in enumerate(names)}
    return {"idid": idid.value, "t_end": t.value, "stats": stats, "y_end": u[:ns].tolist(), "non_finite_f": guarded[0]}


def daemodel_counts(compiled, t_span, tol, nmax=NMAX):
    import daemodel as dm

    sol = dm.solve(compiled, t_span, rtol=tol, atol=tol, stages=3, max_steps=nmax)
    keys = ("steps", "rejected_steps", "attempts", "newton_failures", "jacobian_evaluations", "lu_decompositions")
    y_end = [float(sol[name][-1]) for name in compiled.state_names]
    return {"status": sol.status, "stats": {k: sol.stats[k] for k in keys}, "y_end": y_end}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lib", required=True, help="the libradau5.so built as the module docstring says")
    parser.add_argument("--problems", nargs="+", default=list(PROBLEMS))
    parser.add_argument("--tolerances", nargs="+", type=float, default=list(TOLERANCES))
    parser.add_argument("--nmax", type=int, default=NMAX, help="both codes' step budget")
    parser.add_argument("--out", default=str(HERE / "radau5_counts"))
    args = parser.parse_args(argv)
    from daemodel.files import atomic_write
    from daemodel.problems import PROBLEMS as LIBRARY

    lib = load(args.lib)
    records = []
    for name in args.problems:
        problem = LIBRARY[name]
        compiled = problem.model().compile()
        compiled = compiled.reduced(2) if compiled.index == 3 else compiled  # as dm.solve hands it to radau
        for tol in args.tolerances:
            ours = daemodel_counts(compiled, problem.t_span, tol, args.nmax)
            ours["scd"] = scd(problem, compiled, ours["y_end"])
            runs = {
                "same": radau5(lib, compiled, problem.t_span, tol, nmax=args.nmax),
                "matched": radau5(lib, compiled, problem.t_span, (10 * tol) ** 1.5, nmax=args.nmax),
                "same, THET = 0.1": radau5(lib, compiled, problem.t_span, tol, thet=0.1, nmax=args.nmax),
            }
            for run in runs.values():
                ok = run["idid"] > 0
                y_end = run.pop("y_end")
                difference = np.abs(np.subtract(y_end, ours["y_end"])) / (1 + np.abs(ours["y_end"]))
                run["end_difference"] = float(np.max(difference)) if ok else None
                run["scd"] = scd(problem, compiled, y_end) if ok else None
            records.append({"problem": name, "unknowns": len(compiled.state_names) + len(compiled.algebraic_names),
                            "tol": tol, "radau5": runs, "daemodel": ours})  # fmt: skip
            print(row(records[-1]), flush=True)
    result = {
        "benchmark": "RADAU5's counts beside radau's (issue 26)",
        "command": " ".join(["python", "benchmarks/radau5_counts.py", *(sys.argv[1:] if argv is None else argv)]),
        "radau5": "Assimulo commit e85c74026e3e4599818e72c8bea722db6aef2359, thirdparty/hairer/radau_decsol.c (f2c), "
        "werr calloc fix, benchmarks/radau5_f2c_stubs.c; see the module docstring",
        "records": records,
    }
    atomic_write(Path(args.out).with_suffix(".json"), lambda h: h.write(json.dumps(result, indent=1) + "\n"), text=True)
    print(f"wrote {Path(args.out).with_suffix('.json')}")


def scd(problem, compiled, y_end) -> float | None:
    """The Test Set's significant correct digits of the end states against the problem's published
    reference: -log10 of the largest relative error over the states it gives (None without one)."""
    values = dict(zip(compiled.state_names, y_end, strict=True))
    names = [name for name in problem.reference if name in values]
    if not names:
        return None
    worst = max(abs(values[name] - problem.reference[name]) / abs(problem.reference[name]) for name in names)
    return float(-np.log10(max(worst, 1e-17)))


def row(record: dict) -> str:
    """A markdown row: RADAU5 (same, matched) accepted/rejected / Jacobians / factorisations beside radau's."""
    ours = record["daemodel"]["stats"]

    def counts(run):
        if run["idid"] < 0:
            return f"IDID = {run['idid']}"
        s = run["stats"]
        return f"{s['NACCPT']}/{s['NREJCT']} / {s['NJAC']} / {s['NDEC']}"

    runs = record["radau5"]
    mine = (
        f"{ours['steps']}/{ours['rejected_steps']} / {ours['jacobian_evaluations']} / {ours['lu_decompositions'] // 2}"
    )
    ratio = ""
    if runs["matched"]["idid"] > 0:
        s = runs["matched"]["stats"]
        ratio = f"{ours['steps'] / s['NACCPT']:.2f} / {ours['jacobian_evaluations'] / max(s['NJAC'], 1):.2f}"
    return (
        f"| {record['problem']} | {record['tol']:g} | {counts(runs['same'])} | {counts(runs['matched'])} | "
        f"{counts(runs['same, THET = 0.1'])} | {mine} | {ratio} |"
    )


if __name__ == "__main__":
    main()
