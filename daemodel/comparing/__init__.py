"""Comparing methods: ``compare`` (work-precision tables and plots) and the ``daemodel`` command."""
