"""A pendulum's length and mass from noisy positions: exact sensitivities, the adjoint, and a fit.

The damped Cartesian pendulum of ``daemodel.problems.DAMPED_PENDULUM`` (index 3, solved through
its index-2 reduction)::

    x' = u,  y' = v,  m u' = -lam x - c u,  m v' = -lam y - c v - m g,  0 = x^2 + y^2 - L^2

released from rest at the angle of (0.6, -0.8), with known damping c = 0.3.  The script

1. solves with ``sensitivities=["L", "m"]`` and checks d(x, y, lam)/d(L, m) against central finite
   differences of solves at perturbed values (the initial position moved onto the longer rod by
   ``compiled.consistent``);
2. checks the adjoint gradient of a misfit against the forward sensitivities;
3. fits L and m to positions measured at 50 times with 1 % noise (the truth: L = 1.3, m = 0.7) and
   checks that each estimate lies within two standard errors of the truth;
4. shows the refusal of a fit of m and c together, which only enter as c/m.

Run: python examples/fit.py [--plot PATH]
"""

import argparse

import numpy as np

import daemodel as dm
from daemodel.problems import DAMPED_PENDULUM

TRUE = {"L": 1.3, "m": 0.7}


def measurements(compiled, t, noise: float, seed: int = 1) -> dict:
    """Positions at ``t`` from a tight solve at the true values, plus noise of ``noise`` x L."""
    y0 = compiled.consistent(parameters=TRUE)  # the same angle, on the longer rod
    truth = dm.solve(compiled, (0.0, float(t[-1])), parameters=TRUE, y0=y0, rtol=1e-11, t_eval=np.r_[0.0, t])
    rng = np.random.default_rng(seed)
    return {k: truth[k][1:] + noise * TRUE["L"] * rng.standard_normal(len(t)) for k in ("x", "y")}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plot", help="write the data, the fit and its residuals to this PNG")
    args = parser.parse_args(argv)
    compiled = DAMPED_PENDULUM.model().compile()

    # 1. sensitivities against central differences
    t_eval = np.linspace(0.0, 5.0, 11)
    sol = dm.solve(compiled, (0.0, 5.0), h=0.01, stages=3, newton_tol=1e-14, t_eval=t_eval, sensitivities=["L", "m"])
    print(
        f"solve {1e3 * sol.solve_time:.1f} ms, of which sensitivities {1e3 * sol.stats['sensitivity_seconds']:.1f} ms"
    )
    worst = 0.0
    for name in ("L", "m"):
        delta = 1e-5
        runs = []
        for sign in (1, -1):
            parameters = {name: 1.0 + sign * delta}
            y0 = compiled.consistent(parameters=parameters)
            runs.append(
                dm.solve(
                    compiled,
                    (0.0, 5.0),
                    h=0.01,
                    stages=3,
                    newton_tol=1e-14,
                    t_eval=t_eval,
                    parameters=parameters,
                    y0=y0,
                )
            )
        for output in ("x", "y", "lam"):
            fd = (runs[0][output] - runs[1][output]) / (2 * delta)
            gap = float(np.abs(sol.sensitivity(output, name) - fd).max() / np.abs(fd).max())
            worst = max(worst, gap)
            ours = sol.sensitivity(output, name)[-1]
            print(f"  d{output}/d{name} at t = 5: {ours: .8f}  (central differences: {fd[-1]: .8f})")
    print(f"largest relative gap to central differences: {worst:.1e}")
    assert worst < 1e-6

    # 2. the adjoint gradient of a misfit equals the forward one
    data = measurements(compiled, t_eval[1:], 0.01)
    misfit = {k: np.r_[np.nan, v] for k, v in data.items()}  # no measurement at t0
    gradient = sol.gradient(misfit, ["L", "m"])
    for name in ("L", "m"):
        forward = sum(np.nansum(2 * (sol[k] - misfit[k]) * sol.sensitivity(k, name)) for k in misfit)
        print(f"dJ/d{name}: adjoint {gradient[name]: .12g}, forward {forward: .12g}")
        assert abs(gradient[name] - forward) <= 1e-8 * abs(forward)

    # 3. the fit
    t = np.linspace(0.1, 5.0, 50)
    data = measurements(compiled, t, 0.01)
    fit = dm.fit(compiled, t, data, {"L": (0.5, 3.0), "m": (0.1, 5.0)})
    print(f"\n{fit!r}")
    print("truth:", TRUE)
    for name, value in TRUE.items():
        off = (fit.parameters[name] - value) / fit.std[name]
        print(f"  {name}: {off:+.2f} standard errors from the truth")
        assert abs(off) <= 2
    assert fit.status == "success"

    # 4. what the data cannot tell apart is refused, by name
    try:
        dm.fit(compiled, t, data, {"L": (0.5, 3.0), "m": (0.1, 5.0), "c": 0.3})
    except dm.errors.UnidentifiableError as error:
        print(f"\nm and c together: {error}")
    else:
        raise AssertionError("m and c enter as c/m only: the fit must refuse them")

    if args.plot:
        plot(fit, t, data, args.plot)


def plot(fit, t, data, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 1, figsize=(7, 5), sharex=True, height_ratios=[3, 1])
    sol = fit.solution
    fine = np.linspace(0.0, t[-1], 400)
    curve = sol.at(fine)
    for name, colour in (("x", "tab:blue"), ("y", "tab:orange")):
        axes[0].plot(t, data[name], ".", color=colour, label=f"{name} measured")
        axes[0].plot(fine, curve[name], "-", color=colour, label=f"{name} fitted")
        axes[1].plot(t, fit.residuals[name], ".", color=colour)
    estimates = ", ".join(f"{k} = {v:.4f} ± {fit.std[k]:.4f}" for k, v in fit.parameters.items())
    axes[0].set(ylabel="position", title=f"damped pendulum: {estimates}")
    axes[0].legend(fontsize=8, ncol=2)
    axes[1].axhline(0.0, color="k", lw=0.5)
    axes[1].set(xlabel="t", ylabel="data - model")
    fig.tight_layout()
    from daemodel.files import save_figure

    save_figure(fig, path, "--plot", dpi=110)  # (atomic, checked)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
