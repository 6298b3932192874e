"""RunLock: a live run's folder is refused by name, a dead run's lock is taken over and said so."""

from __future__ import annotations

import json
import os
import socket
import subprocess

import pytest

from unipolicy_rl.training import RunFolderInUse, RunLock
from unipolicy_rl.training.run_lock import LOCK_NAME


def write_lock(folder, pid: int, host: str | None = None) -> None:
    lock = {"pid": pid, "host": host or socket.gethostname(), "started": "2024-01-01T00:00:00+00:00"}
    (folder / LOCK_NAME).write_text(json.dumps(lock) + "\n")


def exited_pid() -> int:
    process = subprocess.Popen(["true"])
    process.wait()  # reaped: the pid names no process any more
    return process.pid


def test_lock_holds_this_process_and_is_removed_on_exit(tmp_path):
    with RunLock(tmp_path):
        held = json.loads((tmp_path / LOCK_NAME).read_text())
        assert held["pid"] == os.getpid()
        assert held["host"] == socket.gethostname()
    assert not (tmp_path / LOCK_NAME).exists()


def test_creates_the_run_folder(tmp_path):
    with RunLock(tmp_path / "new" / "run"):
        assert (tmp_path / "new" / "run" / LOCK_NAME).is_file()


def test_live_lock_is_refused_with_its_pid(tmp_path):
    sleeper = subprocess.Popen(["sleep", "30"])
    try:
        write_lock(tmp_path, sleeper.pid)
        with pytest.raises(RuntimeError, match=rf"in use by a live run \(pid {sleeper.pid}, started") as error:
            with RunLock(tmp_path):
                pass
        assert str(tmp_path) in str(error.value)
        assert json.loads((tmp_path / LOCK_NAME).read_text())["pid"] == sleeper.pid  # untouched
    finally:
        sleeper.kill()
        sleeper.wait()


def test_second_lock_inside_the_first_is_refused(tmp_path):
    with RunLock(tmp_path):
        with pytest.raises(RunFolderInUse, match=f"pid {os.getpid()}"):
            with RunLock(tmp_path):
                pass
        assert (tmp_path / LOCK_NAME).is_file()  # the refused one leaves the holder's lock alone
    assert not (tmp_path / LOCK_NAME).exists()


def test_stale_lock_is_taken_over_and_said_so(tmp_path, capsys):
    dead = exited_pid()
    write_lock(tmp_path, dead)
    with RunLock(tmp_path):
        assert json.loads((tmp_path / LOCK_NAME).read_text())["pid"] == os.getpid()
    assert f"took over a stale lock of pid {dead} (no such process)" in capsys.readouterr().out
    assert not (tmp_path / LOCK_NAME).exists()


@pytest.mark.parametrize("garbage", ["", "not json", '{"pid": -1, "host": "h"}', '{"pid": true, "host": "h"}'])
def test_unreadable_lock_is_taken_over_and_said_so(tmp_path, capsys, garbage):
    (tmp_path / LOCK_NAME).write_text(garbage)
    with RunLock(tmp_path):
        assert json.loads((tmp_path / LOCK_NAME).read_text())["pid"] == os.getpid()
    assert f"took over the unreadable lock {tmp_path / LOCK_NAME}" in capsys.readouterr().out


def test_lock_of_another_host_is_refused_with_how_to_remove_it(tmp_path):
    write_lock(tmp_path, exited_pid(), host="some-other-host")
    with pytest.raises(RunFolderInUse, match="on host 'some-other-host'") as error:
        with RunLock(tmp_path):
            pass
    assert f"delete {tmp_path / LOCK_NAME} by hand" in str(error.value)


def test_lock_replaced_by_someone_else_is_not_removed(tmp_path, capsys):
    with RunLock(tmp_path):
        write_lock(tmp_path, 12345)
    assert json.loads((tmp_path / LOCK_NAME).read_text())["pid"] == 12345
    assert "left" in capsys.readouterr().out


def test_lock_removed_by_someone_else_is_fine(tmp_path):
    with RunLock(tmp_path):
        (tmp_path / LOCK_NAME).unlink()
    assert not (tmp_path / LOCK_NAME).exists()


def test_lock_is_removed_when_the_run_fails(tmp_path):
    with pytest.raises(ValueError, match="boom"):
        with RunLock(tmp_path):
            raise ValueError("boom")
    assert not (tmp_path / LOCK_NAME).exists()
