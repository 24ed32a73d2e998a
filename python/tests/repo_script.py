"""Loads a script of the repository (under tools/ or python/examples/) as a module, for the
tests that check it; the script's file name without `.py` is the module's name."""

import importlib.util
import pathlib

REPO = pathlib.Path(__file__).resolve().parents[2]


def load(relative: str):
    """The script at `relative` (to the repository root), executed as a fresh module."""
    path = REPO / relative
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
