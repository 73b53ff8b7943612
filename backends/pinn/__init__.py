"""The Radau-PINN, one direction: network.py (attention MLP) -> loss.py (the Radau residual) ->
train.py (fits one segment: Levenberg-Marquardt with lm.py's linear systems, or
first_order.py's L-BFGS or Adam) ->
segments.py (the segments in time, one after another or as executor tasks) -> backend.py
(``method="pinn"``: the Solution, with certificate.py's verdict) and surrogate.py (trained
networks: their evaluation and checks; uses segments.py, never the backend), with
surrogate_box.py (training states drawn from a box) and surrogate_files.py (their file).
The user's ``dm.Surrogate`` (training over a box through ensembles, the hybrid solve that falls
back to radau) is daemodel/solving/surrogates.py, built on surrogate.py.

Only :mod:`.config` loads without torch.
"""
