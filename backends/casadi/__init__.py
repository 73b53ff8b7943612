"""casadi's integrators: Radau collocation (:mod:`.collocation`, ``method="casadi-collocation"``)
and IDAS on the index-1 reduction (:mod:`.idas`, ``method="casadi-idas"``), with what both share
in :mod:`.plumbing`.

Both build one casadi integrator per model, output times and settings, kept with the compiled
model (:func:`~.plumbing.cached_integrator`: a sweep or a repeated solve pays the setup once), and
call it once per sample (casadi integrates one initial state per call).

Trust, for both:

1. Nothing casadi prints reaches the user: its evaluation warnings are switched off, and what
   it still prints during a call (IDAS's error text, the root finder's input dump) is captured
   and read for the time of the failure.
2. A failure is one exception line naming the method, the sample, the time and the reason, with
   the fix.  Each module's docstring says what else it checks.
"""
