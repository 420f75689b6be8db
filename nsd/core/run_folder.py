"""One run per folder: a held lock, a log of everything the run prints, no stale leftovers.

:class:`RunFolder` is entered by every command that writes a run or output folder:

* it refuses a path that is a file;
* it takes an exclusive lock (``<folder>/.lock``, ``flock``: released by the kernel when the
  process dies, so a killed run never blocks the next one); a second run on the same
  folder stops at once with the owner named (pid, command, start time);
* with the lock held, temporary folders of earlier runs (``.<name>.partial-*``) are stale
  and removed;
* everything written to stdout and stderr also goes to ``<folder>/run.log`` (progress-bar
  redraws excepted), errors included.
"""

from __future__ import annotations

import datetime as _dt
import fcntl
import io
import logging
import os
import shutil
import socket
import sys
import traceback
from pathlib import Path
from types import TracebackType
from typing import TextIO

from nsd.core.errors import BAD_INPUT_ERRORS, ConfigError, RunFolderBusyError

__all__ = ["LOCK_FILE", "LOG_FILE", "RunFolder"]

log = logging.getLogger(__name__)
LOCK_FILE = ".lock"
LOG_FILE = "run.log"


class _Tee(io.TextIOBase):
    """Writes to a stream and appends the same text (minus ``\\r`` redraws) to a log file."""

    def __init__(self, stream: TextIO, log_file: TextIO) -> None:
        self.stream, self.log_file = stream, log_file

    def write(self, text: str) -> int:
        self.stream.write(text)
        if "\r" not in text:
            self.log_file.write(text)
            self.log_file.flush()
        return len(text)

    def flush(self) -> None:
        self.stream.flush()

    def isatty(self) -> bool:
        return self.stream.isatty()

    def fileno(self) -> int:
        return self.stream.fileno()

    @property
    def encoding(self) -> str:  # type: ignore[override]
        return getattr(self.stream, "encoding", "utf-8")


class RunFolder:
    """Context manager: lock ``folder`` for this process, log to it, clean stale leftovers.

    Args:
        folder: the run or output folder (created).
        prog: the command's name (recorded in the lock and the log).
        key: the config key that named the folder (for messages).
        log: tee stdout/stderr into ``<folder>/run.log``.

    Raises:
        ConfigError: ``folder`` exists and is not a folder.
        RunFolderBusyError: another live process holds the folder.
    """

    def __init__(self, folder: str | os.PathLike, prog: str, key: str = "out",
                 log: bool = True) -> None:
        self.folder, self.prog, self.key, self.log = Path(folder), prog, key, log
        self._fd: int | None = None
        self._streams: tuple[TextIO, TextIO] | None = None
        self._log_file: TextIO | None = None

    def __enter__(self) -> RunFolder:
        if self.folder.exists() and not self.folder.is_dir():
            raise ConfigError(f"{self.key}: {self.folder} is a file, not a folder; give another "
                              f"{self.key}=")
        self.folder.mkdir(parents=True, exist_ok=True)
        self._lock()
        self._remove_stale()
        if self.log:
            self._log_file = open(self.folder / LOG_FILE, "a", encoding="utf-8")
            self._streams = (sys.stdout, sys.stderr)
            sys.stdout = _Tee(sys.stdout, self._log_file)  # type: ignore[assignment]
            sys.stderr = _Tee(sys.stderr, self._log_file)  # type: ignore[assignment]
            self._point_handlers(self._streams, (sys.stdout, sys.stderr))
            stamp = _dt.datetime.now().isoformat(timespec="seconds")
            self._log_file.write(f"--- {stamp} {self.prog} (pid {os.getpid()}): "
                                 f"{' '.join(sys.argv[1:])}\n")
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc is not None and not isinstance(exc, (SystemExit, KeyboardInterrupt)):
            if isinstance(exc, BAD_INPUT_ERRORS):  # bad input: the message (the user sees it too)
                self.write_log(f"error: {exc}")
            else:  # the traceback, for a bug report (the user sees one line)
                self.write_log("".join(traceback.format_exception(kind, exc, tb)))
        if self._streams is not None:
            self._point_handlers((sys.stdout, sys.stderr), self._streams)
            sys.stdout, sys.stderr = self._streams
            self._streams = None
        if self._log_file is not None:
            self._log_file.close()
            self._log_file = None
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    @staticmethod
    def _point_handlers(old: tuple[TextIO, TextIO], new: tuple[TextIO, TextIO]) -> None:
        """Log handlers that write to the console follow it into (or out of) the tee."""
        loggers = [logging.getLogger(), *(lg for lg in logging.Logger.manager.loggerDict.values()
                                          if isinstance(lg, logging.Logger))]
        for lg in loggers:
            for h in lg.handlers:
                if type(h) is logging.StreamHandler and h.stream in old:
                    h.setStream(new[old.index(h.stream)])

    def write_log(self, text: str) -> None:
        """Append ``text`` to run.log only (e.g. a traceback the user is not shown)."""
        if self._log_file is not None:
            self._log_file.write(text if text.endswith("\n") else text + "\n")
            self._log_file.flush()

    @property
    def log_path(self) -> Path:
        return self.folder / LOG_FILE

    def _lock(self) -> None:
        path = self.folder / LOCK_FILE
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            owner = os.read(fd, 4096).decode(errors="replace").strip() or "another process"
            os.close(fd)
            raise RunFolderBusyError(
                f"{self.key}: {self.folder} is in use by {owner}; wait for that run to end or "
                f"give another {self.key}=") from None
        os.ftruncate(fd, 0)
        stamp = _dt.datetime.now().isoformat(timespec="seconds")
        os.write(fd, f"pid {os.getpid()} on {socket.gethostname()} ({self.prog}, started "
                     f"{stamp})\n".encode())
        self._fd = fd

    def _remove_stale(self) -> None:
        """Temporary folders left by dead runs: with the lock held, no live run owns one."""
        for p in [*self.folder.glob(".*.partial-*"), *self.folder.glob(".*.tmp")]:
            shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
            log.info("removed %s, left by an interrupted run", p)
