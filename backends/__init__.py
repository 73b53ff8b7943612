"""Solver backends, installed as ``daemodel.backends``.

Each backend is one module with ``solve(compiled, ...) -> Solution`` and one registry line;
core code never branches on a backend's name.  (The classical solvers and the Radau-PINN
land here with issues 3 and 4.)
"""
