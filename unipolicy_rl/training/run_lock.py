"""One run per run folder: a second run started where a live one still writes is refused by name.

Two runs in one folder would interleave their metrics.csv rows and overwrite each other's
checkpoints, and nothing afterwards could tell which epoch came from which. The lock is a file,
``run.lock``, holding the owner's process id, host name and start time. A lock whose process
has died (killed, crashed, the machine rebooted) is stale: the next run takes it over and says
so, so a crash never needs cleaning up by hand. Liveness can only be checked on the host that
wrote the lock; a lock from another host is refused with the way to remove it by hand.

Creating the file is atomic (``O_CREAT | O_EXCL``), so of two runs starting together one wins.
Taking over a stale lock is a check followed by a replace, so two runs that find the same stale
lock at the same instant can both pass the check; each reads its lock back after the replace
and is refused if it finds the other's, which leaves a window of microseconds, not none.
"""

from __future__ import annotations

import json
import os
import socket
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

LOCK_NAME = "run.lock"


class RunFolderInUse(RuntimeError):
    """Another run holds the folder's lock; the message names the folder and that run."""


@dataclass(frozen=True)
class LockHolder:
    """Who a lock file says holds the folder."""

    pid: int
    host: str
    started: str  # local time, ISO 8601, for the message only

    @classmethod
    def me(cls) -> LockHolder:
        return cls(os.getpid(), socket.gethostname(), datetime.now().astimezone().isoformat(timespec="seconds"))

    def to_text(self) -> str:
        return json.dumps({"pid": self.pid, "host": self.host, "started": self.started}) + "\n"

    @classmethod
    def from_text(cls, text: str) -> LockHolder:
        """Raises ValueError, naming what is wrong, on anything but a lock this module wrote."""
        try:
            fields = json.loads(text)
        except json.JSONDecodeError as error:
            raise ValueError(f"not JSON ({error})") from None
        if not isinstance(fields, dict):
            raise ValueError(f"not a JSON object: {text.strip()[:80]!r}")
        pid, host, started = fields.get("pid"), fields.get("host"), fields.get("started")
        # bool is an int; pid 0 and negative pids address process groups in os.kill.
        if not (isinstance(pid, int) and not isinstance(pid, bool) and pid > 0):
            raise ValueError(f"pid must be a positive integer, got {pid!r}")
        if not isinstance(host, str) or not host:
            raise ValueError(f"host must be a non-empty string, got {host!r}")
        return cls(pid, host, str(started))


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this host (signal 0 checks without signalling)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # it exists, under another user
        return True
    return True


class RunLock:
    """Holds ``run_dir/run.lock`` for the ``with`` block; raises :class:`RunFolderInUse` on
    entry when a live run holds it. On exit the lock is removed only if it is still this
    run's (a lock someone replaced meanwhile is theirs now)."""

    def __init__(self, run_dir: Path | str) -> None:
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / LOCK_NAME
        self._written: str | None = None

    def __enter__(self) -> RunLock:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        mine = LockHolder.me().to_text()
        try:
            descriptor = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            self._take_over_if_stale(mine)
        else:
            with os.fdopen(descriptor, "w") as file:
                file.write(mine)
        self._written = mine
        return self

    def __exit__(self, *exc_info) -> None:
        written, self._written = self._written, None
        try:
            current = self.path.read_bytes()  # bytes: a garbage file must not fail the run's exit
            if written is not None and current == written.encode():
                self.path.unlink(missing_ok=True)
            else:
                print(f"left {self.path} in place: another process replaced this run's lock", flush=True)
        except FileNotFoundError:
            return
        except OSError as error:  # an unwritable folder: the run's own error, if any, is the one to see
            print(f"could not remove {self.path} ({type(error).__name__}: {error}); a later run takes it over "
                  f"once this process has ended", flush=True)

    def _take_over_if_stale(self, mine: str) -> None:
        try:
            text = self.path.read_text()
        except FileNotFoundError:  # its owner removed it just now: the folder is free
            self._replace(mine)
            return
        try:
            holder = LockHolder.from_text(text)
        except (ValueError, UnicodeDecodeError) as error:
            self._replace(mine)
            print(f"took over the unreadable lock {self.path} ({error})", flush=True)
            return
        self._refuse_if_live(holder)
        self._replace(mine)
        print(f"took over a stale lock of pid {holder.pid} (no such process) in {self.run_dir}", flush=True)

    def _refuse_if_live(self, holder: LockHolder) -> None:
        if holder.host != socket.gethostname():
            raise RunFolderInUse(
                f"{self.run_dir} is locked by pid {holder.pid} on host {holder.host!r} (started {holder.started}), "
                f"whose liveness cannot be checked from {socket.gethostname()!r}: if that run is over, delete "
                f"{self.path} by hand; else wait for it, or start in another folder")
        if process_alive(holder.pid):
            raise RunFolderInUse(
                f"{self.run_dir} is in use by a live run (pid {holder.pid}, started {holder.started}): "
                f"wait for it, or start in another folder")

    def _replace(self, mine: str) -> None:
        temporary = self.path.with_name(f".{LOCK_NAME}.{os.getpid()}.tmp")
        try:
            temporary.write_text(mine)
            os.replace(temporary, self.path)
        finally:
            temporary.unlink(missing_ok=True)
        try:
            current = self.path.read_text(errors="replace")
        except FileNotFoundError:
            current = ""
        if current != mine:  # another run replaced the same stale lock at the same moment, after this one
            raise RunFolderInUse(f"{self.run_dir}: another run took over its stale lock at the same moment "
                                 f"(the lock now reads {current.strip()!r}): wait for it, or start in another folder")
