"""The Radau-PINN, one direction: network.py (attention MLP) -> loss.py (the Radau residual) ->
train.py (fits one segment: Levenberg-Marquardt with lm.py's linear systems, L-BFGS or Adam) ->
segments.py (the segments in time, one after another or as engine tasks) -> backend.py
(``method="pinn"``: the Solution, with certificate.py's verdict) and surrogate.py (trained
networks as a reusable solver; uses segments.py, never the backend).

Only :mod:`.config` loads without torch.
"""
