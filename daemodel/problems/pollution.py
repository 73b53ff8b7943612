"""The pollution problem from the Test Set for IVP Solvers (a stiff ODE of 20 equations: 25 reactions
of an air pollution model), with the test set's reference at t = 60."""

from __future__ import annotations

from daemodel.problems.problem import Problem

# ---- Pollution, index 0 ------------------------------------------------------------------------
#
# Source: F. Mazzia and C. Magherini, Test Set for Initial Value Problem Solvers, release 2.4
# (Dept. of Mathematics, Univ. of Bari, February 2008), the ODE problem "Pollution" (pollu.f,
# revision 1.2, 2006/10/02), the chemistry of the air pollution model of the Dutch National
# Institute of Public Health and Environmental Protection (RIVM), as in Verwer (1994); read in
# deTestSet's copy: src/Ex_pollution.f (polfunc: the reaction rates r1..r25 and the equations;
# the reference at t = 60, computed by RADAU5 in quadruple precision at rtol = atol = h0 = 1.1e-18)
# and R/ex_pollution.R (k1..k25, y(0), [0, 60]).  The unknowns keep the test set's order y1..y20
# under Verwer's species: NO2, NO, O3P, O3, HO2, OH, HCHO, CO, ALD, MEO2, C2O3, CO2, PAN, CH3O,
# HNO3, O1D, SO2, SO4, NO3, N2O5.
POLLUTION_SPECIES = (
    "NO2", "NO", "O3P", "O3", "HO2", "OH", "HCHO", "CO", "ALD", "MEO2",
    "C2O3", "CO2", "PAN", "CH3O", "HNO3", "O1D", "SO2", "SO4", "NO3", "N2O5",
)  # fmt: skip
POLLUTION_PARAMETERS = {
    "k1": 0.35, "k2": 26.6, "k3": 1.23e4, "k4": 8.6e-4, "k5": 8.2e-4,
    "k6": 1.5e4, "k7": 1.3e-4, "k8": 2.4e4, "k9": 1.65e4, "k10": 9.0e3,
    "k11": 2.2e-2, "k12": 1.2e4, "k13": 1.88, "k14": 1.63e4, "k15": 4.8e6,
    "k16": 3.5e-4, "k17": 1.75e-2, "k18": 1.0e8, "k19": 4.44e11, "k20": 1.24e3,
    "k21": 2.1, "k22": 5.78, "k23": 4.74e-2, "k24": 1.78e3, "k25": 3.12,
}  # fmt: skip
# polfunc's rates: r_k = k_k times the species it consumes (y's test set numbers)
_RATE_SPECIES = (
    (1,), (2, 4), (5, 2), (7,), (7,), (7, 6), (9,), (9, 6), (11, 2), (11, 1),
    (13,), (10, 2), (14,), (1, 6), (3,), (4,), (4,), (16,), (16,), (17, 6),
    (19,), (19,), (1, 4), (19, 1), (20,),
)  # fmt: skip
# polfunc's equations: f_i = the rates that produce species i minus those that consume it
_PRODUCED = {
    1: (2, 3, 9, 11, 12, 22, 25), 2: (1, 21), 3: (1, 17, 19, 22), 4: (15,), 5: (4, 4, 6, 7, 13, 20),
    6: (3, 18, 18), 7: (13,), 8: (4, 5, 6, 7), 9: (), 10: (7, 9), 11: (8, 11), 12: (9,), 13: (10,),
    14: (12,), 15: (14,), 16: (16,), 17: (), 18: (20,), 19: (23, 25), 20: (24,),
}  # fmt: skip
_CONSUMED = {
    1: (1, 10, 14, 23, 24), 2: (2, 3, 9, 12), 3: (15,), 4: (2, 16, 17, 23), 5: (3,), 6: (6, 8, 14, 20),
    7: (4, 5, 6), 8: (), 9: (7, 8), 10: (12,), 11: (9, 10), 12: (), 13: (11,), 14: (13,), 15: (),
    16: (18, 19), 17: (20,), 18: (), 19: (21, 22, 24), 20: (25,),
}  # fmt: skip


def _rate(k: int) -> str:
    return "*".join((f"k{k}", *(POLLUTION_SPECIES[i - 1] for i in _RATE_SPECIES[k - 1])))


def _pollution_rhs(i: int) -> str:
    expr = " + ".join(_rate(k) for k in _PRODUCED[i]) or "0"
    return expr + "".join(f" - {_rate(k)}" for k in _CONSUMED[i])


# pollu.f, subroutine solut: y(1..20) at t = 60
_POLLUTION_T1 = (
    0.5646255480022769e-01, 0.1342484130422339e00, 0.4139734331099427e-08, 0.5523140207484359e-02,
    0.2018977262302196e-06, 0.1464541863493966e-06, 0.7784249118997964e-01, 0.3245075353396018e00,
    0.7494013383880406e-02, 0.1622293157301561e-07, 0.1135863833257075e-07, 0.2230505975721359e-02,
    0.2087162882798630e-03, 0.1396921016840158e-04, 0.8964884856898295e-02, 0.4352846369330103e-17,
    0.6899219696263405e-02, 0.1007803037365946e-03, 0.1772146513969984e-05, 0.5682943292316392e-04,
)  # fmt: skip

POLLUTION = Problem(
    name="pollution",
    odes={name: _pollution_rhs(i) for i, name in enumerate(POLLUTION_SPECIES, start=1)},
    algebraics=(),
    constraints={},
    parameters=POLLUTION_PARAMETERS,
    initial={name: 0.0 for name in POLLUTION_SPECIES}
    | {"NO": 0.2, "O3": 0.04, "HCHO": 0.1, "CO": 0.3, "ALD": 0.01, "SO2": 0.007},
    t_span=(0.0, 60.0),
    compare_steps=200,  # (h = 0.3: 5.3 digits with radau at a fixed step; the fast species O3P and O1D
    # equilibrate within each step, which the L-stable Radau IIA allows)
    index=0,
    reference=dict(zip(POLLUTION_SPECIES, _POLLUTION_T1, strict=True)),
    # O1D is 4.4e-17 at t = 60, below any tolerance a solver is given: its relative error measures
    # nothing the solver controls, so the digits are read from the other 19 species
    scd_names=tuple(name for name in POLLUTION_SPECIES if name != "O1D"),
    source="Pollution problem (stiff ODE of 20 equations, the RIVM air pollution chemistry, Verwer 1994) of "
    "the Test Set for IVP Solvers (Mazzia & Magherini, Univ. of Bari), pollu.f rev. 1.2 (2006); reference at "
    "t = 60 from the test set",
)
