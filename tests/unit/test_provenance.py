"""``provenance``: the code's fingerprint among the versions (a kept predictive, pixel noise or evaluation of another
build of the same version number is not taken for this one's)."""

from __future__ import annotations

from uncertsplat.provenance import fingerprint_of, source_fingerprint, versions


def test_the_fingerprint_follows_the_code_and_nothing_else(tmp_path):
    (tmp_path / "pkg" / "native").mkdir(parents=True)
    (tmp_path / "pkg" / "a.py").write_text("x = 1\n")
    (tmp_path / "pkg" / "native" / "k.cpp").write_text("int f();\n")
    first = fingerprint_of(tmp_path / "pkg")
    assert len(first) == 12 and first == fingerprint_of(tmp_path / "pkg")
    (tmp_path / "pkg" / "notes.txt").write_text("mine")  # not code
    (tmp_path / "pkg" / "__pycache__").mkdir()
    (tmp_path / "pkg" / "__pycache__" / "a.py").write_text("cached")
    assert fingerprint_of(tmp_path / "pkg") == first
    (tmp_path / "pkg" / "native" / "k.cpp").write_text("int f(int);\n")  # a kernel edited
    second = fingerprint_of(tmp_path / "pkg")
    assert second != first
    (tmp_path / "pkg" / "a.py").rename(tmp_path / "pkg" / "c.py")  # the same bytes under another name
    assert fingerprint_of(tmp_path / "pkg") not in (first, second)


def test_an_unreadable_file_is_named_not_raised(tmp_path, monkeypatch):
    """A file that cannot be read (no permission, deleted while the folder is walked) counts by its name: the
    versions of every command are read through it, and an OSError there stopped them."""
    from pathlib import Path

    (tmp_path / "a.py").write_text("x = 1\n")
    (tmp_path / "b.py").write_text("y = 2\n")
    readable = fingerprint_of(tmp_path)
    real = Path.read_bytes

    def refuse(self):
        if self.name == "b.py":
            raise PermissionError(13, "Permission denied")
        return real(self)

    monkeypatch.setattr(Path, "read_bytes", refuse)
    unreadable = fingerprint_of(tmp_path)
    assert len(unreadable) == 12 and unreadable != readable


def test_versions_carry_the_packages_fingerprint():
    v = versions()
    assert v["source"] == source_fingerprint() and len(v["source"]) == 12 and {"uncertsplat", "python"} <= set(v)
