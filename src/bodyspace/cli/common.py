"""What every ``bodyspace`` command shares: the one error exit, the one progress helper, the one
output policy and the common options.

* **Error exit** (``guarded``): every command runs inside it. A ``BodyspaceError`` (the user's
  input), an ``OSError`` (a file system refusal) or a ``MemoryError`` ends in one line
  ``error: ...`` and exit code 2; anything else is a bug in bodyspace and ends in one line and
  exit code 3 (``BODYSPACE_DEBUG=1`` shows the traceback). Warnings raised while a command runs
  (also in worker threads) are collected and printed once each, one line, without Python's
  file/line decoration.
* **Output policy** (``check_file_output``, ``check_folder_output``, ``output_folder``): an
  existing output is refused unless ``--force``; with ``--force`` only an output bodyspace wrote
  (``bodyspace.atomic``: the ``.bodyspace`` marker of folders, the signature of files) is
  replaced; files and folders are written under a temporary name and renamed; leftovers of
  killed runs are removed by the next run; permissions follow the umask.
"""

from __future__ import annotations

import contextlib
import functools
import os
import re
import time
import traceback
import warnings
from pathlib import Path
from typing import Callable, Iterable, Iterator

import typer
import typer.exceptions
from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    Progress,
    ProgressColumn,
    TextColumn,
    TimeElapsedColumn,
)
from rich.text import Text

from bodyspace.atomic import (
    SIGNATURES,
    atomic_dir,
    check_replaceable_folder,
    is_own_file,
    temporary_name,
)
from bodyspace.errors import BodyspaceError, OutputError

console = Console(stderr=True)  # progress, warnings, errors, "wrote ..." lines
out_console = Console()  # results: tables, JSON, CSV

EXIT_USER_ERROR = 2
EXIT_INTERNAL_ERROR = 3
MESH_SUFFIXES = (".obj", ".ply", ".glb")
# Bodies decoded at once by `sample` and `crowd` (bounds memory: 64 bodies of 19k vertices are
# 30 MB), and bodies drawn on a contact sheet (a sheet of thousands is unreadable and would
# hold them all).
SAMPLE_CHUNK = 64
SHEET_MAX = 100

AssetsOption = typer.Option(None, "--assets", help="An MPFB2-style asset folder to use instead of the cache "
                                                    "(or set BODYSPACE_ASSETS).")
ForceOption = typer.Option(False, "--force", help="Replace an existing output, but only one bodyspace wrote "
                                                  "(a folder with its .bodyspace marker, a file with its signature).")


def SeedOption(help: str = "Random seed (an integer >= 0).", default: int = 0):
    """A ``--seed`` option: integers >= 0 (numpy refuses negative seeds)."""
    return typer.Option(default, "--seed", min=0, help=help)


# ----------------------------------------------------------------------------- error exit
def print_error(message: str) -> None:
    """One line on stderr; soft_wrap: never break a file path across lines."""
    console.print(f"[red]error:[/red] {escape(message)}", soft_wrap=True, highlight=False)


def fail(exc: Exception | str) -> None:
    """Print ``exc`` as one ``error:`` line and exit with code 2."""
    print_error(str(exc))
    raise typer.Exit(code=EXIT_USER_ERROR)


def _os_error_message(exc: OSError) -> str:
    where = exc.filename if exc.filename is not None else "a file"
    reason = exc.strerror or str(exc)
    return f"cannot write or read {where}: {reason}"


_FLOATING = re.compile(r"encountered in|overflow|divide by zero|invalid value", re.IGNORECASE)
_QUIET = (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning)


def report_warnings(caught: Iterable[warnings.WarningMessage]) -> None:
    """Each distinct warning once, one line; numpy's floating-point warnings folded into one."""
    seen: dict[str, int] = {}
    floating: dict[str, int] = {}
    for w in caught:
        if issubclass(w.category, _QUIET):
            continue
        text = " ".join(str(w.message).split())
        target = floating if issubclass(w.category, RuntimeWarning) and _FLOATING.search(text) else seen
        target[text] = target.get(text, 0) + 1
    for text, count in seen.items():
        console.print(f"[yellow]warning:[/yellow] {escape(text)}" + (f" ({count} times)" if count > 1 else ""),
                      soft_wrap=True, highlight=False)
    if floating:
        total = sum(floating.values())
        console.print(f"[yellow]warning:[/yellow] {total} floating-point warning(s) inside the computation "
                      f"({escape('; '.join(floating))}); the numbers shown above are the ones reached",
                      soft_wrap=True, highlight=False)


def guarded(fn: Callable) -> Callable:
    """The one error exit around a command function (see the module docstring)."""
    @functools.wraps(fn)
    def run(*args, **kwargs):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                return fn(*args, **kwargs)
            except (typer.Exit, typer.Abort, typer.exceptions.TyperException, KeyboardInterrupt):
                raise
            except BodyspaceError as exc:
                fail(exc)
            except MemoryError as exc:
                fail(f"out of memory{f' ({exc})' if str(exc) else ''}; ask for fewer bodies or samples "
                     "(e.g. a smaller -n / --samples) or free memory")
            except OSError as exc:
                fail(_os_error_message(exc))
            except Exception as exc:  # a bug: one line, unless asked for the traceback
                if os.environ.get("BODYSPACE_DEBUG"):
                    traceback.print_exc()
                print_error(f"internal error ({type(exc).__name__}: {exc}); this is a bug in bodyspace, please "
                            "report it with the command you ran (BODYSPACE_DEBUG=1 shows the traceback)")
                raise typer.Exit(code=EXIT_INTERNAL_ERROR)
            finally:
                report_warnings(caught)
    return run


# ----------------------------------------------------------------------------- progress
def remaining_seconds(first: tuple[float, float], last: tuple[float, float]) -> float | None:
    """Seconds left at ``last`` = (time, fraction done), at the rate since ``first``; None
    before there is a rate.

    The rate is the whole run's since its first report, not a recent window: a chunk of work
    can take longer than any window (so a windowed rate has no samples and shows nothing), the
    start-up before the first report (imports, compiling) is not work that is left, and a
    resumed run's jump to the fraction done before the interruption is not speed.
    """
    (t0, f0), (t, f) = first, last
    if f <= f0 or t <= t0:
        return None
    return max(0.0, (1.0 - f) * (t - t0) / (f - f0))


class _RemainingColumn(ProgressColumn):
    """``remaining_seconds`` at the last report, counted down since it (``-:--:--`` before a rate)."""

    def render(self, task) -> Text:
        left = task.fields.get("eta_left")
        if left is None or task.finished:
            return Text("-:--:--" if not task.finished else "0:00:00", style="progress.remaining")
        left = max(0, int(round(left - (time.monotonic() - task.fields["eta_at"]))))
        return Text(f"{left // 3600}:{left // 60 % 60:02d}:{left % 60:02d}", style="progress.remaining")


@contextlib.contextmanager
def progress(description: str, eta: bool = False) -> Iterator[Callable[[str, float], None]]:
    """A rich progress bar on stderr driven by ``callback(message, fraction)``; ``eta``: with the
    remaining time (``remaining_seconds``: the rate since the first report)."""
    columns = [TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"),
               TimeElapsedColumn()]
    if eta:
        columns += [TextColumn("eta"), _RemainingColumn()]
    with Progress(*columns, TextColumn("{task.fields[message]}"), console=console, transient=False) as bar:
        task = bar.add_task(description, total=1.0, message="", eta_left=None, eta_at=0.0)
        first: list[tuple[float, float]] = []

        def callback(message: str, fraction: float) -> None:
            now = time.monotonic()
            first[:] = first or [(now, fraction)]
            bar.update(task, completed=fraction, message=message,
                       eta_left=remaining_seconds(first[0], (now, fraction)), eta_at=now)

        yield callback


# ----------------------------------------------------------------------------- output policy
def _check_location(path: Path, flag: str) -> None:
    """Refuse ``.``/``..``/empty names, a parent that is a file, and a folder we cannot write in."""
    if path.name in ("", ".", ".."):
        raise OutputError(f"{flag} {path}: names an existing folder itself, expected a new name inside it "
                          f"(e.g. {flag} {Path(path, 'out')})")
    ancestor = path.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise OutputError(f"{flag} {path}: {ancestor} is a file, not a folder; choose a path inside a folder")
    # A real probe, not os.access: root passes os.access everywhere, yet cannot write in /proc.
    probe = temporary_name(ancestor / "probe")
    try:
        os.close(os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
        os.unlink(probe)
    except OSError as exc:
        raise OutputError(f"{flag} {path}: cannot write in {ancestor} ({exc.strerror or exc}); "
                          "choose another path") from None


def check_file_output(path: Path, flag: str, force: bool, suffixes: tuple[str, ...] | None = None,
                      example: str = "out") -> None:
    """Raise OutputError unless ``path`` may be written as a file output of option ``flag``.

    suffixes: the accepted endings (e.g. ``(".png",)``); example: a file name for messages.
    """
    path = Path(path)
    _check_location(path, flag)
    if path.is_dir():
        raise OutputError(f"{flag} {path}: is a folder, expected a file name (e.g. {flag} {path / example})")
    if suffixes is not None and path.suffix.lower() not in suffixes:
        raise OutputError(f"{flag} {path}: expected a file name ending in {', '.join(suffixes)}")
    if path.exists() or path.is_symlink():
        if not force:
            raise OutputError(f"{flag} {path}: already exists; pass --force to replace it (only a file "
                              "bodyspace wrote is replaced)")
        if not is_own_file(path):
            why = ("this bodyspace cannot recognise its own " + path.suffix + " files"
                   if path.suffix.lower() not in SIGNATURES else "it has no bodyspace signature")
            raise OutputError(f"{flag} {path}: exists and was not written by bodyspace ({why}); --force replaces "
                              "only bodyspace's own outputs; remove it yourself or choose another path")


def check_folder_output(path: Path, flag: str, force: bool, kind: str) -> None:
    """Raise OutputError unless ``path`` may be written as a folder output (``kind`` in its marker)."""
    path = Path(path)
    _check_location(path, flag)
    if path.exists() or path.is_symlink():
        if not path.is_dir():
            raise OutputError(f"{flag} {path}: is a file, expected a folder name")
        if not force:
            raise OutputError(f"{flag} {path}: already exists; pass --force to replace it (only a folder "
                              "bodyspace wrote is replaced)")
        check_replaceable_folder(path, kind, flag="--force")


@contextlib.contextmanager
def output_folder(path: Path, flag: str, force: bool, kind: str) -> Iterator[Path]:
    """Check ``path`` (``check_folder_output``), then yield a temporary folder that becomes
    ``path`` (with the ``.bodyspace`` marker of ``kind``) when the block completes."""
    check_folder_output(path, flag, force, kind)
    with atomic_dir(path, overwrite=force, kind=kind, flag="--force") as tmp:
        yield tmp


def check_choice(value: str, flag: str, choices: Iterable[str]) -> str:
    """``value`` lower-cased if it is one of ``choices``; else a BodyspaceError naming ``flag``."""
    choices = tuple(choices)
    if value.lower() not in choices:
        raise BodyspaceError(f"{flag} {value!r}: expected one of {', '.join(choices)}")
    return value.lower()

