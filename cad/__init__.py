"""Layouts: load, validate and import target CAD layouts (``nanoasm.layout/1``)."""
