"""How every command starts and ends.

* :func:`check_command_line` composes the app's config from ``sys.argv`` and checks every
  value (:func:`nsd.core.validation.check_config`) before Hydra starts the job: a bad key,
  a value of the wrong type or range, or an argument that is not ``key=value`` stops the
  command at once with one line naming it (exit status 2).
* :func:`reported` wraps a command's work: bad input (:class:`~nsd.core.errors.NSDError`,
  missing or clashing files) is one line on stderr and exit status 2; Ctrl-C is exit 130;
  anything else is a bug: one line on stderr (exit status 1), the traceback only in the
  run's log, never on the user's screen.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import tempfile
import traceback
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import NoReturn

from hydra.errors import HydraException
from omegaconf.errors import OmegaConfBaseException

import nsd
from nsd.core.config import compose_app
from nsd.core.errors import BAD_INPUT_ERRORS, NSDError
from nsd.core.run_folder import RunFolder
from nsd.core.validation import check_config

__all__ = ["BAD_INPUT", "BUG", "Report", "check_command_line", "fail", "reported"]

log = logging.getLogger(__name__)
BAD_INPUT = 2  # exit status of bad input (as argparse)
BUG = 1  # exit status of an internal error


def fail(prog: str, message: str, status: int = BAD_INPUT) -> NoReturn:
    """Print ``<prog>: error: <message>`` (one line) and exit with ``status``."""
    one_line = " ".join(str(message).split())
    print(f"{prog}: error: {one_line}", file=sys.stderr, flush=True)
    sys.exit(status)


def _hydra_message(e: BaseException) -> str:
    """Hydra's and OmegaConf's composition errors in one line, cause first."""
    parts = [str(e).splitlines()[0]] if str(e) else []
    cause = e.__cause__ or e.__context__
    if cause is not None and str(cause):
        parts.append(str(cause).splitlines()[0])
    text = "; ".join(parts)
    if "is not in struct" in text or "Could not override" in text:
        text += " (is the key spelled right? `--cfg job` prints every key)"
    if "Ambiguous value" in text:  # a comma makes a sweep list of a path
        text += (" (a value holding a comma, such as a path, must be quoted: "
                 "key=\"'/my,folder/x'\")")
    return text


def check_command_line(prog: str, app: str, argv: Sequence[str] | None = None) -> None:
    """Compose ``app``'s config from the command line and check every value.

    ``--version`` prints the toolkit's version. Hydra's own modes (``--help``, ``--cfg``,
    ``-m`` sweeps, any other argument starting with ``-``) are left to Hydra.

    Exits with status 2 and one line naming the argument or key on bad input.
    """
    args = list(sys.argv[1:] if argv is None else argv)
    if args in (["--version"], ["-V"]):
        print(f"{prog} (nsd-netepu) {nsd.__version__}")
        sys.exit(0)
    if any(a.startswith("-") for a in args):
        return
    for a in args:
        if "=" not in a and not a.startswith("~"):
            fail(prog, f"argument {a!r} is not key=value; if a path holds spaces, quote the "
                       f"whole argument: key=\"'/my folder/x'\"")
    try:
        cfg = compose_app(app, args)
    except (HydraException, OmegaConfBaseException) as e:
        fail(prog, _hydra_message(e))
    try:
        check_config(app, cfg, args)
    except NSDError as e:
        fail(prog, str(e))
    except (HydraException, OmegaConfBaseException) as e:
        fail(prog, _hydra_message(e))


class Report:
    """Where a command's internal error is recorded: ``log_path`` is set once the run's
    :class:`~nsd.core.run_folder.RunFolder` is open (it writes the traceback there)."""

    def __init__(self) -> None:
        self.log_path: Path | None = None

    def attach(self, folder: RunFolder) -> RunFolder:
        """``with RunFolder(...) as f: report.attach(f)``: returns ``folder``."""
        self.log_path = folder.log_path if folder.log else None
        return folder


@contextlib.contextmanager
def reported(prog: str) -> Iterator[Report]:
    """Turn what a command raises into one line and an exit status.

    Usage::

        with reported("nsd-run") as report, RunFolder(out, "nsd-run") as folder:
            report.attach(folder)
            ...
    """
    report = Report()
    try:
        yield report
    except SystemExit:
        raise
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr, flush=True)
        sys.exit(130)
    except BAD_INPUT_ERRORS as e:
        fail(prog, str(e))
    except (HydraException, OmegaConfBaseException) as e:
        fail(prog, _hydra_message(e))
    except Exception as e:  # a bug: the user sees one line, the log keeps the traceback
        where = report.log_path
        if where is None:
            fd, name = tempfile.mkstemp(prefix=f"{prog}-error-", suffix=".log")
            with os.fdopen(fd, "w") as f:
                f.write(traceback.format_exc())
            where = Path(name)
        fail(prog, f"internal error ({type(e).__name__}: {e}); the traceback is in {where}; "
                   "please report it with that file", status=BUG)
