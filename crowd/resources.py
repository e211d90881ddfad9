"""Where the shipped data lives: the shaders, the built-in assets and the scenes.

In a source checkout, and in the editable install that runs from it, they are the top-level folders
shaders/, assets/ and scenes/ beside the packages. An installed wheel has no project folder above its
packages, so it carries them inside this package as crowd/_data/<folder> (pyproject.toml's
[tool.setuptools.package-dir]). The packaged copy is looked for first: beside an installed crowd, the
folder above is site-packages, where a folder called assets/ may belong to anyone.

Plain paths, not importlib.resources traversables: callers glob, read, report and (assets, from the
generator) write them, and pip always installs a wheel unpacked. Standard library only, importing
nothing from the project, so every floor may ask.
"""

from __future__ import annotations

from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent


def _data_dir(name: str) -> Path:
    packaged = _PACKAGE / "_data" / name
    return packaged if packaged.is_dir() else _PACKAGE.parent / name


SHADER_DIR = _data_dir("shaders")
ASSET_DIR = _data_dir("assets")
SCENE_DIR = _data_dir("scenes")
