"""Bundled example layouts and scenes, installed with the package."""

from importlib.resources import files
from pathlib import Path


def path(name: str) -> Path:
    """Path of a bundled example file, e.g. ``path("bowtie.toml")``."""
    return Path(str(files(__name__).joinpath(name)))
