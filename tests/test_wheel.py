"""A non-editable install works: the wheel carries the shaders, the built-in zombie and the scenes
(pyproject.toml maps them into crowd/_data/), and the installed package finds them with neither the
source tree nor the editable install in reach.

The wheel is built from a copy of the checkout in a temporary folder (an in-tree build would leave
build/ and crowd.egg-info/ here) and installed into a fresh virtual environment whose only link to this
one is a .pth line naming this environment's site-packages, for the dependencies. A .pth line adds a
folder to sys.path without running the .pth files inside it, so the editable install's finder, which
one of those starts, is not installed there.
"""

from __future__ import annotations

import configparser
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import tomllib
import zipfile
from pathlib import Path
from typing import NamedTuple

import pytest

from conftest import ROOT

DATA = "crowd/_data"  # where the wheel carries shaders/, assets/ and scenes/ (crowd/resources.py)
PACKAGES = ("crowd", "app", "bench")
# What a checkout holds beside its sources: the venv, git, caches, earlier build outputs.
NOT_SOURCE = shutil.ignore_patterns(".*", "__pycache__", "*.pyc", "*.egg-info", "build", "dist", "out")
# What pip says when this environment lacks pyproject.toml's build requirements, and when it could not
# fetch them either (offline, no index): the one case in which this machine cannot build a wheel.
NOT_HERE = "Some build dependencies for"
NOT_FETCHED = "to install build dependencies did not run successfully"


def _pip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pip", "--disable-pip-version-check", *args],
                          capture_output=True, text=True, timeout=300, env=_clean_env())


def _clean_env() -> dict[str, str]:
    """The environment minus what would point Python back at the source tree."""
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP")}


def _build_wheel(source: Path, out: Path) -> Path:
    """This environment's setuptools when it meets pyproject.toml's build requirements (offline, fast),
    otherwise an isolated build as `pip install .` does, which fetches them."""
    local = _pip("wheel", str(source), "--no-deps", "--no-build-isolation", "--check-build-dependencies", "-w", str(out))
    if local.returncode != 0:
        if NOT_HERE not in local.stdout + local.stderr:
            pytest.fail("building the wheel with this environment's setuptools failed:\n" + local.stdout[-3000:] + local.stderr[-3000:])
        isolated = _pip("wheel", str(source), "--no-deps", "-w", str(out))
        if isolated.returncode != 0:
            text = isolated.stdout + isolated.stderr
            if NOT_FETCHED in text:
                missing = next(line for line in (local.stdout + local.stderr).splitlines() if NOT_HERE in line)
                missing = missing.strip().removeprefix("ERROR: ").rstrip(".")
                pytest.skip(f"cannot build a wheel here: pip could not fetch the build requirements, and here {missing}")
            pytest.fail("building the wheel failed:\n" + text[-6000:])
    wheels = list(out.glob("crowd-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    source = tmp_path_factory.mktemp("checkout") / "crowd"
    shutil.copytree(ROOT, source, ignore=NOT_SOURCE)
    return _build_wheel(source, tmp_path_factory.mktemp("wheel"))


class Install(NamedTuple):
    venv: Path
    site: Path  # its site-packages


@pytest.fixture(scope="module")
def installed(wheel, tmp_path_factory) -> Install:
    """A fresh venv with the wheel installed."""
    venv = tmp_path_factory.mktemp("venv")
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    python = venv / "bin" / "python"
    site = Path(subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               capture_output=True, text=True, check=True).stdout.strip())
    ours = dict.fromkeys(sysconfig.get_paths()[k] for k in ("purelib", "platlib"))
    (site / "dependencies.pth").write_text("".join(f"{p}\n" for p in ours))
    # pip --python runs pip in the new venv, so the console scripts start the new venv's interpreter.
    out = _pip("--python", str(python), "install", "--no-deps", "--no-index", "-q", str(wheel))
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    return Install(venv, site)


def test_the_wheel_carries_the_packages_the_data_and_the_entry_points(wheel):
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
        scripts = configparser.ConfigParser()
        scripts.read_string(z.read(entry_points).decode())
    modules = {p.relative_to(ROOT).as_posix() for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}
    missing = sorted(modules - names)
    assert not missing, f"modules missing from the wheel (a package absent from [tool.setuptools] packages?): {missing}"
    data = [f"{DATA}/{p.relative_to(ROOT).as_posix()}" for p in
            [*(ROOT / "shaders").rglob("*.glsl"), ROOT / "assets" / "zombie.glb", *(ROOT / "scenes").glob("*.toml")]]
    assert any("/bench/" in name for name in data)  # shaders in subfolders are among them
    missing = sorted(set(data) - names)
    assert not missing, f"data missing from the wheel: {missing}"
    assert "crowd/py.typed" in names
    assert {n.split("/")[0] for n in names} == {*PACKAGES, entry_points.split("/")[0]}  # nothing else
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert {"crowd-demo", "crowd-bench"} <= declared.keys()
    assert dict(scripts["console_scripts"]) == declared


# Run by the installed interpreter: where everything came from, and the data read through the runtime's
# own paths. build_character is replaced so that a missing zombie.glb fails instead of being regenerated.
PROBE = """
import json, sys
import app, bench, crowd
from crowd import resources
from crowd.asset import gltf, zombie
from crowd.gl import load_shader
from crowd.scene import load_scene

def regenerated(*args, **kwargs):
    raise AssertionError("the built-in zombie was regenerated: zombie.glb not found")

zombie.build_character = regenerated
character = gltf.load_character(None)
shaders = sorted(p.relative_to(resources.SHADER_DIR).as_posix() for p in resources.SHADER_DIR.rglob("*.glsl"))
print(json.dumps({
    "modules": [m.__file__ for m in (app, bench, crowd)],
    "dirs": [str(d) for d in (resources.SHADER_DIR, resources.ASSET_DIR, resources.SCENE_DIR)],
    "asset": str(zombie.ASSET_PATH),
    "character": [character.name, len(character.clips)],
    "shaders": {name: len(load_shader(name)) for name in shaders if name.endswith((".vert.glsl", ".frag.glsl", ".comp.glsl"))},
    "scenes": {p.name: load_scene(p).name for p in sorted(resources.SCENE_DIR.glob("*.toml"))},
    "editable_finders": [str(f) for f in sys.meta_path if "__editable__" in str(f)],
    "path": sys.path,
}))
"""


def _is_under(path: str | Path, folder: Path) -> bool:
    return Path(path).resolve().is_relative_to(folder.resolve())


def test_the_installed_package_finds_its_data_outside_the_source_tree(installed, tmp_path):
    out = subprocess.run([installed.venv / "bin" / "python", "-c", PROBE], cwd=tmp_path, env=_clean_env(),
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    probe = json.loads(out.stdout.splitlines()[-1])
    assert all(_is_under(m, installed.site) for m in probe["modules"]), probe["modules"]
    assert probe["editable_finders"] == [] and ROOT.resolve() not in [Path(p).resolve() for p in probe["path"] if p], probe["path"]
    assert all(_is_under(d, installed.site / DATA) and Path(d).is_dir() for d in probe["dirs"]), probe["dirs"]
    assert _is_under(probe["asset"], installed.site) and probe["character"][0] == "zombie" and probe["character"][1] > 0
    assert "bench/panda_actor.vert.glsl" in probe["shaders"] and "skin.vert.glsl" in probe["shaders"]
    assert probe["scenes"].keys() == {p.name for p in (ROOT / "scenes").glob("*.toml")}


def test_the_installed_crowd_demo_runs_headless_from_another_folder(installed, tmp_path, gl_context):
    scene = installed.site / DATA / "scenes" / "horde.toml"  # the default scene: every feature on
    out = subprocess.run([installed.venv / "bin" / "crowd-demo", "--headless", "--frames", "2", "--size", "64x36", "--agents", "3",
                          "--scene", str(scene), "--screenshot", "out.png"],
                         cwd=tmp_path, env=_clean_env(), capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    assert (tmp_path / "out.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
