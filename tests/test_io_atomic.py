"""Atomic writes: all or nothing, for a file and for a folder."""

import os
import uuid

import pytest

from securegs_warp.io import atomic as atomic_module
from securegs_warp.io import atomic_open, atomic_write
from securegs_warp.io.atomic import atomic_folder, folder_leftovers


def test_writes_content(tmp_path):
    target = tmp_path / "a.bin"
    atomic_write(target, lambda f: f.write(b"hello"))
    assert target.read_bytes() == b"hello"
    assert os.listdir(tmp_path) == ["a.bin"]


def test_failed_writer_leaves_no_file(tmp_path):
    target = tmp_path / "a.bin"

    def half_then_crash(f):
        f.write(b"half")
        raise RuntimeError("disk on fire")

    with pytest.raises(RuntimeError, match="disk on fire"):
        atomic_write(target, half_then_crash)
    assert os.listdir(tmp_path) == []


def test_failed_writer_keeps_the_old_content(tmp_path):
    target = tmp_path / "a.bin"
    target.write_bytes(b"old")
    with pytest.raises(KeyboardInterrupt):
        with atomic_open(target) as f:
            f.write(b"new, but unfinished")
            raise KeyboardInterrupt
    assert target.read_bytes() == b"old"
    assert os.listdir(tmp_path) == ["a.bin"]
    with atomic_open(target) as f:
        f.write(b"new")
    assert target.read_bytes() == b"new"


def test_permissions_follow_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        atomic_write(tmp_path / "a.bin", lambda f: f.write(b"x"))
    finally:
        os.umask(old)
    if os.name == "posix":
        assert (tmp_path / "a.bin").stat().st_mode & 0o777 == 0o644


# ----------------------------------------------------------------------------------------------
# Folders
# ----------------------------------------------------------------------------------------------


def make_folder(path, files):
    path.mkdir()
    for name, content in files.items():
        (path / name).write_bytes(content)


def snapshot(path):
    return {p.name: p.read_bytes() for p in path.iterdir()}


@pytest.fixture(params=["exchange", "two renames"])
def publish_mode(request, monkeypatch):
    """Publishing with an atomic swap (Linux), and with the rename-aside fallback of other systems."""
    if request.param == "two renames":
        monkeypatch.setattr(atomic_module, "_exchange", lambda a, b: False)
    return request.param


def test_folder_is_replaced_as_a_whole(tmp_path, publish_mode):
    target = tmp_path / "model"
    make_folder(target, {"a": b"old a", "b": b"old b"})
    with atomic_folder(target) as folder:
        assert folder.parent == tmp_path and folder.name.startswith(".model.tmp-")
        assert list(folder.iterdir()) == []
        (folder / "a").write_bytes(b"new a")
        (folder / "c").write_bytes(b"new c")
        assert snapshot(target) == {"a": b"old a", "b": b"old b"}  # nothing visible before the end
    assert snapshot(target) == {"a": b"new a", "c": b"new c"}  # b is gone: the folder is replaced
    assert os.listdir(tmp_path) == ["model"]


def test_folder_is_created_with_its_parents(tmp_path):
    target = tmp_path / "x" / "y" / "model"
    with atomic_folder(target) as folder:
        (folder / "a").write_bytes(b"a")
    assert snapshot(target) == {"a": b"a"}
    assert os.listdir(target.parent) == ["model"]


@pytest.mark.parametrize("exception", [RuntimeError, KeyboardInterrupt])
def test_failed_folder_keeps_the_old_one(tmp_path, publish_mode, exception):
    target = tmp_path / "model"
    make_folder(target, {"a": b"old a", "b": b"old b"})
    with pytest.raises(exception):
        with atomic_folder(target) as folder:
            (folder / "a").write_bytes(b"new a")
            raise exception
    assert snapshot(target) == {"a": b"old a", "b": b"old b"}
    assert os.listdir(tmp_path) == ["model"]


def test_failed_publish_keeps_the_old_folder(tmp_path, monkeypatch):
    # Without an atomic swap the old folder is renamed aside first; if the new one then cannot take
    # its place, the old one is put back.
    target = tmp_path / "model"
    make_folder(target, {"a": b"old a"})
    monkeypatch.setattr(atomic_module, "_exchange", lambda a, b: False)
    real_rename = os.rename

    def rename(src, dst):
        if ".tmp-" in os.fspath(src):
            raise OSError("no space left for a rename")
        real_rename(src, dst)

    monkeypatch.setattr(atomic_module.os, "rename", rename)
    with pytest.raises(OSError, match="no space left"):
        with atomic_folder(target) as folder:
            (folder / "a").write_bytes(b"new a")
    assert snapshot(target) == {"a": b"old a"}
    assert os.listdir(tmp_path) == ["model"]


def test_leftovers_of_a_crash_go_with_the_next_write(tmp_path, publish_mode):
    target = tmp_path / "model"
    make_folder(target, {"a": b"old a"})
    # What a kill -9 can leave: a folder under construction, an old folder renamed aside.
    make_folder(tmp_path / f".model.tmp-{uuid.uuid4().hex}", {"a": b"half"})
    make_folder(tmp_path / f".model.old-{uuid.uuid4().hex}", {"a": b"older"})
    # Not leftovers of this target: kept.
    make_folder(tmp_path / ".model.tmp-mine", {})
    make_folder(tmp_path / f".other.tmp-{uuid.uuid4().hex}", {})
    assert len(folder_leftovers(target)) == 2
    with atomic_folder(target) as folder:
        (folder / "a").write_bytes(b"new a")
    assert folder_leftovers(target) == []
    assert sorted(os.listdir(tmp_path)) == sorted([".model.tmp-mine", next(
        n for n in os.listdir(tmp_path) if n.startswith(".other.")), "model"])
    assert snapshot(target) == {"a": b"new a"}


def test_a_leftover_is_removed_only_after_the_new_folder_is_in_place(tmp_path, monkeypatch):
    # Without an atomic swap, a crash between the two renames leaves the only complete copy under
    # .model.old-*; a later write that fails must not have deleted it.
    target = tmp_path / "model"
    aside = tmp_path / f".model.old-{uuid.uuid4().hex}"
    make_folder(aside, {"a": b"old a"})
    with pytest.raises(RuntimeError):
        with atomic_folder(target) as folder:
            (folder / "a").write_bytes(b"new a")
            raise RuntimeError
    assert snapshot(aside) == {"a": b"old a"}


def test_folder_keeps_its_link_and_permissions(tmp_path):
    real = tmp_path / "real"
    make_folder(real, {"a": b"old"})
    if os.name != "posix":
        pytest.skip("symbolic links and permission bits are POSIX")
    real.chmod(0o550)  # read-only to its owner too: the new content is written elsewhere
    link = tmp_path / "link"
    link.symlink_to(real)
    with atomic_folder(link) as folder:
        (folder / "a").write_bytes(b"new")
    assert link.is_symlink() and snapshot(link) == {"a": b"new"}
    assert real.stat().st_mode & 0o777 == 0o550
    assert sorted(os.listdir(tmp_path)) == ["link", "real"]


def test_a_file_is_not_replaced_by_a_folder(tmp_path):
    target = tmp_path / "model"
    target.write_bytes(b"a file")
    with pytest.raises(NotADirectoryError):
        with atomic_folder(target):
            raise AssertionError("not reached")
    assert target.read_bytes() == b"a file"
    assert os.listdir(tmp_path) == ["model"]


def test_relative_and_dot_paths(tmp_path, monkeypatch):
    target = tmp_path / "model"
    make_folder(target, {"a": b"old"})
    monkeypatch.chdir(target)
    with atomic_folder("../model/.") as folder:
        (folder / "a").write_bytes(b"new")
    assert snapshot(target) == {"a": b"new"}
    assert os.listdir(tmp_path) == ["model"]


def test_swap_is_atomic_where_the_system_has_one(tmp_path):
    if not atomic_module._exchange(tmp_path, tmp_path):
        pytest.skip("this system or file system has no renameat2(RENAME_EXCHANGE)")
    make_folder(tmp_path / "a", {"x": b"1"})
    make_folder(tmp_path / "b", {"y": b"2"})
    assert atomic_module._exchange(tmp_path / "a", tmp_path / "b")
    assert snapshot(tmp_path / "a") == {"y": b"2"} and snapshot(tmp_path / "b") == {"x": b"1"}
