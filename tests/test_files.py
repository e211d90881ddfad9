"""Atomic writes keep a file's mode (or give a new one what a plain open would), and lose nothing."""

from __future__ import annotations

import os

from crowd.files import atomic_write_bytes


def test_a_new_file_gets_the_umask_mode_and_an_old_one_keeps_its_own(tmp_path):
    path = tmp_path / "scene.toml"
    mask = os.umask(0o022)
    try:
        atomic_write_bytes(path, b"a")
        assert path.stat().st_mode & 0o777 == 0o644 and path.read_bytes() == b"a"
        os.chmod(path, 0o600)
        atomic_write_bytes(path, b"b")
        assert path.stat().st_mode & 0o777 == 0o600 and path.read_bytes() == b"b"
    finally:
        os.umask(mask)
    assert [p.name for p in tmp_path.iterdir()] == ["scene.toml"]  # no temporary file left
