"""Declaring a model: the Model a user writes (by name), the strict parser of its strings, the
functions it may use and the symbols it hands out."""
