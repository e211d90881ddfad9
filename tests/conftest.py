from pathlib import Path

import moderngl
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


@pytest.fixture(scope="session", autouse=True)
def cache_folder(tmp_path_factory):
    """The caches (impostor atlases, generated LODs) of a test session in a folder of its own, not the user's."""
    import os

    os.environ["CROWD_CACHE_DIR"] = str(tmp_path_factory.mktemp("cache"))
    yield


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


@pytest.fixture
def compute_context(gl_context):
    """The session's context where it runs compute shaders (GL 4.3); the test skips elsewhere."""
    from crowd.gl import has_compute

    if not has_compute(gl_context):
        pytest.skip("this test needs GL 4.3 compute shaders")
    return gl_context


@pytest.fixture
def no_compute_features(monkeypatch):
    """Every way into compute shaders, storage buffers, image load/store and multi-draw-indirect fails loudly while set."""

    def refused(*args, **kwargs):
        raise AssertionError("a GL 4.3 feature was used on the 4.1 path")

    monkeypatch.setattr(moderngl.Context, "compute_shader", refused)
    monkeypatch.setattr(moderngl.Context, "memory_barrier", refused)
    monkeypatch.setattr(moderngl.Buffer, "bind_to_storage_buffer", refused)
    monkeypatch.setattr(moderngl.Texture, "bind_to_image", refused)
    monkeypatch.setattr(moderngl.TextureArray, "bind_to_image", refused)
    # (moderngl's indirect draws are glMultiDraw*Indirect, GL 4.3, which a 4.1 context does not have)
    monkeypatch.setattr(moderngl.VertexArray, "render_indirect", refused)
    # The entry points the transform-feedback cull loads through ctypes: GL 4.1 core's only.
    import crowd.draw.feedback_cull as feedback
    from crowd import gl

    core_41 = {"glUseProgram", "glBindVertexArray", "glBindBufferBase", "glBeginTransformFeedback", "glEndTransformFeedback",
               "glDrawArrays", "glBindBuffer", "glDrawElementsIndirect", "glGenTransformFeedbacks", "glDeleteTransformFeedbacks",
               "glBindTransformFeedback", "glDrawTransformFeedbackStream"}

    def loaded(name, prototype):
        if name not in core_41:
            raise AssertionError(f"{name} is not GL 4.1 core")
        return gl.current_context_function(name, prototype)

    monkeypatch.setattr(feedback, "current_context_function", loaded)
    monkeypatch.setattr(feedback, "_api", None)  # loaded again, through the check


# -- GL objects alive (the leak tests count them): the soak's census

from bench.soak import gl_census  # noqa: E402,F401


def khronos_issues(path) -> dict:
    """The Khronos glTF-Validator's report (its "issues": numErrors, numWarnings, messages) on a file;
    skips the test where the validator is not installed (.ci/run installs it with npm)."""
    import json
    import shutil
    import subprocess

    node = shutil.which("node")
    script = ROOT / ".ci" / "node" / "node_modules" / "gltf-validator"
    if not node or not script.is_dir():
        pytest.skip("Khronos glTF-Validator not installed (.ci/run installs it with npm)")
    js = (
        "const v=require(process.argv[1]);const fs=require('fs');"
        "v.validateBytes(new Uint8Array(fs.readFileSync(process.argv[2]))).then(r=>{"
        "console.log(JSON.stringify(r.issues));}).catch(e=>{console.error(String(e));process.exit(2);});"
    )
    out = subprocess.run([node, "-e", js, str(script), str(path)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)
