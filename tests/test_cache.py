"""crowd.cache: the one rule for what is kept on disk (impostor atlases, generated LODs)."""

import numpy as np
import pytest

from crowd.cache import CacheError, cache_dir, checksum, read_arrays, write_arrays


def test_arrays_round_trip_bit_for_bit(tmp_path):
    arrays = {"a": np.arange(10, dtype=np.int64), "b": np.linspace(0, 1, 7, dtype=np.float32).reshape(7, 1), "name": np.array("walk")}
    write_arrays(tmp_path / "x.npz", arrays)
    back = read_arrays(tmp_path / "x.npz")
    assert set(back) == set(arrays)
    for k in arrays:
        assert back[k].dtype == arrays[k].dtype and np.array_equal(back[k], arrays[k])


@pytest.mark.parametrize("damage", ["truncated", "zeroed tail", "foreign", "changed array"])
def test_a_damaged_file_is_one_line_naming_it(tmp_path, damage):
    path = tmp_path / "x.npz"
    write_arrays(path, {"a": np.arange(1000, dtype=np.int64)})
    data = path.read_bytes()
    if damage == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "zeroed tail":
        path.write_bytes(data[:-300] + bytes(300))
    elif damage == "foreign":
        path.write_bytes(b"not a zip at all")
    else:  # a valid archive whose array no longer matches the checksum stored beside it
        np.savez(path, a=np.arange(1000, dtype=np.int64) + 1, checksum=np.array(checksum([np.arange(1000, dtype=np.int64)])))
    with pytest.raises(CacheError) as err:
        read_arrays(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_the_cache_folder(monkeypatch, tmp_path):
    monkeypatch.delenv("CROWD_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert cache_dir("lods") == tmp_path / "crowd" / "lods" and cache_dir("impostors") == tmp_path / "crowd" / "impostors"
    monkeypatch.setenv("CROWD_CACHE_DIR", str(tmp_path / "all"))
    assert cache_dir("lods") == cache_dir("impostors") == tmp_path / "all"
