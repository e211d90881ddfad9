from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SHARED_GLTF = ROOT.parent / "shared" / "gltf"


def shared_files():
    """Third-party test files from ../shared/gltf (never committed); empty when the folder is absent."""
    if not SHARED_GLTF.is_dir():
        return []
    return sorted(p for p in SHARED_GLTF.iterdir() if p.suffix in (".glb", ".gltf"))


def shared(name: str) -> Path:
    path = SHARED_GLTF / name
    if not path.is_file():
        pytest.skip(f"{path} is absent (third-party test files live outside the project)")
    return path


@pytest.fixture(scope="session")
def zombie():
    from crowd.asset.gltf import load_character

    return load_character()


@pytest.fixture(scope="session")
def gl_context():
    from crowd.gl import GLUnavailable, headless_context

    try:
        ctx = headless_context()
    except GLUnavailable as exc:
        pytest.skip(str(exc))
    yield ctx
    ctx.release()


# -- GL objects alive (the leak tests count them): the soak's census

from bench.soak import gl_census  # noqa: E402,F401
