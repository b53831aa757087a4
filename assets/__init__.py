"""The files hapticloud ships and reads at run time: scenes, the robot model, the CAN database,
parameter presets and icons (``hapticloud.assets``).

They are found through the installed package (:mod:`importlib.resources`), so a wheel, an
editable install and the desktop bundle read the same files whatever the current directory.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path


def asset_path(*parts: str) -> Path:
    """The shipped file or folder ``parts`` (e.g. ``asset_path("scenes", "wall.toml")``).

    A real path on disk, because Pinocchio, Open3D and cantools open files by name: every way
    hapticloud is installed (wheel, editable, bundle) unpacks the package into a folder.
    """
    return Path(str(files(__name__).joinpath(*parts)))
