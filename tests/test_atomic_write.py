"""Outputs are written whole or not at all (:func:`nlyap_opt.kernel.jsonio.write_atomic`)."""

import os
import stat

import pytest

from nlyap_opt.kernel.errors import ConfigError
from nlyap_opt.kernel.jsonio import write_atomic, write_figure, write_files_atomic


def test_a_new_file_has_a_plain_writes_permissions_and_an_old_one_keeps_its_own(tmp_path):
    umask = os.umask(0o022)
    os.umask(umask)
    new = write_atomic(tmp_path / "new.json", "{}")
    assert stat.S_IMODE(new.stat().st_mode) == 0o666 & ~umask
    old = tmp_path / "old.json"
    old.write_text("x")
    old.chmod(0o600)
    write_atomic(old, "y")
    assert old.read_text() == "y" and stat.S_IMODE(old.stat().st_mode) == 0o600


def test_a_link_to_a_file_is_replaced_and_a_link_to_a_device_refused(tmp_path):
    target = tmp_path / "target.json"
    target.write_text("keep")
    link = tmp_path / "link.json"
    link.symlink_to(target)
    write_atomic(link, "new")
    assert target.read_text() == "keep" and link.read_text() == "new" and not link.is_symlink()
    if os.path.exists("/dev/null"):
        dev = tmp_path / "dev.json"
        dev.symlink_to("/dev/null")
        with pytest.raises(ConfigError, match="not a regular file"):
            write_atomic(dev, "x")
        assert dev.is_symlink()


def test_a_long_name_is_written_and_nothing_is_left_beside_it(tmp_path):
    name = "n" * 240 + ".json"
    write_atomic(tmp_path / name, "1")
    assert [p.name for p in tmp_path.iterdir()] == [name]


def test_files_that_belong_together_keep_their_old_contents_when_a_write_fails(tmp_path):
    a, b = tmp_path / "a.h", tmp_path / "a.c"
    a.write_text("old a")
    b.write_text("old b")

    class Boom:   # bytes() of it fails: the second file cannot be written
        def __bytes__(self):
            raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space"):
        write_files_atomic({a: "new a", b: Boom()})
    assert a.read_text() == "old a" and b.read_text() == "old b"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.c", "a.h"]


def test_a_figure_is_written_in_the_format_of_its_suffix(tmp_path):
    plt = pytest.importorskip("matplotlib.pyplot")
    fig = plt.figure()
    try:
        assert write_figure(fig, tmp_path / "f.png").read_bytes()[:4] == b"\x89PNG"
        assert write_figure(fig, tmp_path / "f.pdf").read_bytes()[:4] == b"%PDF"
    finally:
        plt.close(fig)
