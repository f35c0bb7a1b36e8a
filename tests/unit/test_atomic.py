"""Atomic writes and run-folder locks (``io.atomic``): temp names, stale temp files, a lock this process
holds, errors raised from an OSError, output paths under a file."""

from __future__ import annotations

import errno
import os
import stat

import pytest

from uncertsplat.errors import UserError, WriteFailed
from uncertsplat.io import atomic


class TestTempNames:
    def test_a_name_of_exactly_the_limit_is_kept_whole(self):
        name = "n" * atomic.TEMP_STEM
        assert atomic.temp_stem(name) == name
        longer = "n" * (atomic.TEMP_STEM + 1)
        stem = atomic.temp_stem(longer)
        assert len(stem) == atomic.TEMP_STEM and stem.startswith("n" * (atomic.TEMP_STEM - 9) + "~")

    def test_stale_temp_files_of_either_writer_are_removed_and_nothing_else(self, tmp_path):
        # mkstemp's 8 random characters are lower-case letters, digits and '_'
        stale = [".run.json.ab_d_f_h.tmp", ".view_000.x1y2z3w4.tmp.exr", ".model.________.tmp"]
        kept = ["run.json", ".run.json.abcdefg.tmp", ".run.json.abcdefgh.tmp.", "x.abcdefgh.tmp", ".hidden"]
        for name in stale + kept:
            (tmp_path / name).write_text("x")
        (tmp_path / ".dir.abcdefgh.tmp").mkdir()  # a folder of a temp name is not a temp file
        removed = atomic.remove_stale_temp_files(tmp_path, tmp_path / "missing")
        assert sorted(p.name for p in removed) == sorted(stale)
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted(kept + [".dir.abcdefgh.tmp"])

    def test_a_temp_file_made_by_atomic_write_matches_the_stale_pattern(self, tmp_path, monkeypatch):
        seen = []

        def write(tmp):
            seen.append(os.path.basename(tmp))
            raise KeyboardInterrupt  # a killed writer: its temp file would be left

        for _ in range(20):  # random names: some hold '_'
            with pytest.raises(KeyboardInterrupt):
                atomic.atomic_write_via(tmp_path / "view_000.exr", write)
        assert all(atomic._TEMP_NAME.match(n) for n in seen), seen


class TestLocks:
    def test_a_lock_this_process_holds_has_no_other_holder(self, tmp_path):
        run = tmp_path / "run"
        with atomic.run_lock(run, "test"):
            assert atomic.lock_holder(run) is None
            with atomic.run_lock(run, "test"):  # re-entered: still this process's
                assert atomic.lock_holder(run) is None
        assert atomic.lock_holder(run) is None and not run.exists()

    def test_an_output_folder_under_a_file_is_refused(self, tmp_path):
        (tmp_path / "file").write_text("x")
        with pytest.raises(UserError, match="is a file, not a folder"):
            atomic.check_output_folder(tmp_path / "file" / "sub" / "run")
        with pytest.raises(UserError, match="the output path is a file"):
            atomic.check_output_folder(tmp_path / "file")
        atomic.check_output_folder(tmp_path / "new" / "run")  # nothing there yet: fine


class TestWriteErrors:
    def test_an_oserror_during_a_runtimeerror_is_a_clear_write_failure(self, tmp_path):
        """torch.save reports a full disk as a RuntimeError raised while handling the file's OSError (its
        context, not its cause): a clear WriteFailed, not a traceback, and no temp file left."""

        def write(tmp):
            try:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            except OSError:
                raise RuntimeError("[enforce fail at inline_container.cc] unexpected pos")  # noqa: B904

        with pytest.raises(WriteFailed, match="the disk is full") as info:
            atomic.atomic_write_via(tmp_path / "model.pt", write, what="checkpoint")
        assert info.value.space and list(tmp_path.iterdir()) == []

        def plain(tmp):
            raise RuntimeError("plain")

        with pytest.raises(RuntimeError, match="plain"):  # a RuntimeError of no OSError stays what it is
            atomic.atomic_write_via(tmp_path / "model.pt", plain)
        assert list(tmp_path.iterdir()) == []


class TestPermissions:
    """Outputs get the permissions the process's umask gives any file it creates (mkstemp and mkdtemp make
    0600 and 0700: unreadable to other users of a shared disk)."""

    def test_an_atomic_write_has_the_usual_file_mode(self, tmp_path):
        path = atomic.atomic_write_text(tmp_path / "a.json", "{}\n")
        assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~atomic.current_umask()
        assert path.read_text() == "{}\n"

    def test_a_temp_folder_has_the_usual_folder_mode(self, tmp_path):
        folder = atomic.temp_folder(".stage-", tmp_path)
        assert folder.parent == tmp_path and folder.name.startswith(".stage-")
        assert stat.S_IMODE(folder.stat().st_mode) == 0o777 & ~atomic.current_umask()

    def test_the_umask_is_the_process_s(self):
        mask = os.umask(0)
        os.umask(mask)
        assert atomic.current_umask() == mask


class TestStaging:
    def test_a_killed_run_s_staging_folders_are_removed_and_the_new_one_at_the_end(self, tmp_path):
        stale = tmp_path / "_staging_123"
        (stale / "sub").mkdir(parents=True)
        (stale / "sub" / "x").write_text("x")
        other = tmp_path / "_other_1"
        other.mkdir()
        with atomic.staging_folder(tmp_path, "_staging_") as staging:
            assert staging == tmp_path / f"_staging_{os.getpid()}" and not stale.exists() and other.exists()
            (staging / "out").mkdir(parents=True)
        assert not staging.exists() and other.exists()
