"""Solving: ``solve`` (one entry point for every method), solves cut at switches and events, and
ensembles on one machine or on Ray."""
