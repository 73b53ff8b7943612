"""The Radau-PINN: network.py (attention MLP), loss.py (Radau residual), train.py (segments,
optimizers), surrogate.py (trained networks as a reusable solver), backend.py (``method="pinn"``).

Only :mod:`.config` loads without torch.
"""
