"""Parameter estimation: :func:`daemodel.fit` and its result."""
