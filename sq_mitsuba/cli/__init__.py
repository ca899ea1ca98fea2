"""The ``sq-mitsuba`` command line: one parser, one subcommand per module in this package.

Each module ``sq_mitsuba/cli/<name>.py`` defines ``register(subparsers)``, which adds its
subcommand, named like the module, and sets ``func`` (taking the parsed
``argparse.Namespace``, returning an exit code). Commands stay thin: they parse, call the
library, and report. Heavy imports (Mitsuba) happen inside the command. Options whose defaults
come from a library config class import that class's module (often torch) when the parser is
built, so :func:`main` builds only the parser of the command it runs; for the command list of
``sq-mitsuba --help`` a module may define ``HELP`` (its one-line help) and import its config
classes inside ``register``, and is then listed without being registered.

A closed stdout or stderr (``sq-mitsuba predict ... | head -1``, ``... 2>&1 | head -1``) is not
a failed run: what the command prints after the reader has gone is dropped, the run finishes
and keeps its files, and the exit code is that of the run (0 on success), not an error (see
:func:`_closed_stdout_is_quiet`, :func:`_closed_stderr_is_quiet`).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import os
import pkgutil
import signal
import sys
import threading
import traceback
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

from sq_mitsuba.machine import LaunchRanks, launch_ranks
from sq_mitsuba.outputs import interrupted
from sq_mitsuba.render.backend import BackendError, check_variant_environment
from sq_mitsuba.version import __version__

EXIT_ERROR = 2
#: Exit code of an unexpected exception (a bug): reported in one line, with the hint below.
EXIT_INTERNAL = 1
EXIT_INTERRUPTED = 130
#: What to do after an interrupt, for the commands (and actions) that take up where they
#: stopped; the others start over.
RESUME_HINTS = {
    "train": "the same command with --resume continues from last.pt",
    "eval": "the same command with --resume continues from its journal in --out",
    "dataset render": "the same command again takes up where it stopped",
    "dataset fit-parts": "the same command again takes up where it stopped",
    "models generate": "the same command again takes up where it stopped",
    "study illumination": "the same command again takes up where it stopped",
    "study passes": "the same command again takes up where it stopped",
    "predict": "an image's files are whole once its pose.json is written, a pass's once "
               "sequence.assembly.json is; the same command again writes them all",
}


def _resume_hint(args: argparse.Namespace) -> str | None:
    """:data:`RESUME_HINTS`' line for the command run, its action included."""
    action = next((getattr(args, name) for name in ("dataset_command", "models_command",
                                                    "study") if getattr(args, name, None)),
                  None)
    if args.command == "train" and getattr(args, "out", None) is not None \
            and not (Path(args.out) / "last.pt").is_file():
        # Stopped before its first save: there is no step to take up (a best.pt of a
        # validation before it would stop a rerun in that folder: it says what to do).
        if (Path(args.out) / "best.pt").is_file():
            return ("no last.pt was saved: move best.pt away to start again there, or choose "
                    "another --out")
        return "no step was saved yet: the same command without --resume starts it again"
    return RESUME_HINTS.get(args.command if action is None else f"{args.command} {action}")
#: The global flag (before the command) and the environment variable that show tracebacks.
TRACEBACK_FLAG = "--traceback"
TRACEBACK_ENV = "SQ_MITSUBA_TRACEBACK"
TRACEBACK_HINT = (f"rerun with 'sq-mitsuba {TRACEBACK_FLAG} ...' (or {TRACEBACK_ENV}=1) "
                  "for the traceback")
#: Commands whose ``--out`` is all or nothing (:func:`sq_mitsuba.outputs.all_or_nothing`): a
#: folder, or one file; stray temporary files go at start-up, a failed run's output with it.
ALL_OR_NOTHING = {"eval": "folder", "predict": "folder", "fit": "folder", "report": "folder",
                  "study": "folder", "export": "file"}
#: What a failed run of a command keeps in its --out (finished work a rerun resumes): eval's
#: journal; a study's renders, evaluations and journals.
KEEP_ON_FAILURE = {"eval": (".eval_partial",),
                   "study": (".passes_partial", "models", "renders", "evals")}
#: What each of those commands writes in its --out folder, as patterns of paths in it (``*``
#: within one name, a last ``**`` anything below): a failed run deletes only the files of
#: these names it added (and temporary files), and the folders it made once empty, never a
#: file someone saved there meanwhile (:func:`sq_mitsuba.outputs.all_or_nothing`'s
#: ``outputs``). tests/test_user_files_kept.py checks them against the modules' own lists.
OUTPUT_NAMES = {
    "eval": ("per_image.csv", "per_model.csv", "per_model.md", "summary.csv", "summary.md",
             "per_model.png", "qualitative.png", "consistency.png", "eval.json",
             "mesh_ranking.csv", ".eval_partial/*"),
    "predict": ("*.assembly.json", "*.obj", "*.glb", "*.pose.json", "*.overlay.png",
                "sequence.png", "colmap/*.txt"),
    "fit": ("assembly.json", "assembly.glb", "fit.png", "fit_log.json"),
    "report": ("report.md", "report.csv"),
    "study": ("models/**", "renders/**", "evals/**", ".passes_partial/*", "per_image.csv",
              "illumination.*", "lighting.*", "study.json", "per_frame.csv", "summary.csv",
              "summary.md", "quality_vs_frames.png", "passes.json"),
}


class CLIError(Exception):
    """A user-facing failure: printed as one line, exit code 2."""


def command_names() -> list[str]:
    """The subcommands: one per module of this package (``_``-prefixed ones excluded)."""
    return sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_"))


class OneLineErrors(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line, as every other error of the tool
    (argparse prints the whole usage block first): ``sq-mitsuba COMMAND: error: ... (see
    sq-mitsuba COMMAND --help)``, exit code :data:`EXIT_ERROR`. Subcommands' parsers are of
    the same class (argparse makes them of their parent's)."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_ERROR, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser(command: str | None = None, listing: bool = False) -> argparse.ArgumentParser:
    """The ``sq-mitsuba`` parser with every subcommand registered in full.

    Args:
        command: register only this subcommand in full; the others by name only, without
            importing their modules.
        listing: list the subcommands whose module has ``HELP`` by name and help only (enough
            for ``sq-mitsuba --help``); the others are registered in full.
    """
    parser = OneLineErrors(
        prog="sq-mitsuba",
        description="Superquadric abstraction of spacecraft from single images, with Mitsuba 3.",
        epilog=(f"Errors are one line: bad input exits with code {EXIT_ERROR}, an internal "
                f"error (a bug) with code {EXIT_INTERNAL}. To see the full traceback instead, "
                f"give {TRACEBACK_FLAG} before the command (sq-mitsuba {TRACEBACK_FLAG} fit "
                f"...) or set the environment variable {TRACEBACK_ENV}=1. A closed standard "
                "output or error (a pipe whose reader has gone) is not an error: the run finishes, "
                "keeps its files and exits as it would have."),
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}",
                        help="print the package version and exit")
    parser.add_argument(
        TRACEBACK_FLAG, action="store_true",
        help="on an error, raise it with its full traceback instead of printing one line "
             f"(also: {TRACEBACK_ENV}=1)")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in command_names():
        if command is not None and name != command:
            subparsers.add_parser(name)
            continue
        module = importlib.import_module(f"{__name__}.{name}")
        if listing and command is None and hasattr(module, "HELP"):
            subparsers.add_parser(name, help=module.HELP)
            continue
        module.register(subparsers)
    return parser


def _one_line(error: BaseException) -> str:
    if isinstance(error, OSError) and error.strerror and error.filename is not None:
        # A raw operating-system error: "<file>: <what>", not "[Errno 21] Is a directory: ...".
        where = error.filename2 if error.filename2 is not None else error.filename
        return f"{where}: {error.strerror[:1].lower()}{error.strerror[1:]}"
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return "; ".join(lines) or type(error).__name__


def _speaker(command: str) -> str:
    """Who speaks in a message: ``sq-mitsuba COMMAND``, and in a process of a multi-process
    run (torchrun's ``RANK`` > 0) its rank: each process of such a run prints its own errors
    and warnings (one may fail alone), so they must say whose they are."""
    try:
        ranks = launch_ranks()
    except ValueError:  # said by main's own check: untagged here
        ranks = LaunchRanks()
    return f"sq-mitsuba {command}" + (f" (rank {ranks.rank} of {ranks.size})"
                                      if ranks.rank > 0 and ranks.distributed else "")


def _warning_printer(command: str):
    """A ``warnings.showwarning`` that prints a warning as one line, ``sq-mitsuba COMMAND:
    warning: ...``, without Python's file, line number and source line."""

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        text = _one_line(message) if isinstance(message, Warning) else " ".join(
            str(message).split())
        try:
            print(f"{_speaker(command)}: warning: {text}", file=file or sys.stderr)
        except OSError:  # no stderr to write to: as Python's own does, say nothing
            pass

    return show


def traceback_from_environment() -> bool:
    """Whether ``SQ_MITSUBA_TRACEBACK`` asks for tracebacks (set, and not 0/false/no/off)."""
    value = os.environ.get(TRACEBACK_ENV, "").strip().lower()
    return value not in ("", "0", "false", "no", "off")


@contextlib.contextmanager
def _terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM (``kill``, ``timeout``, a scheduler's stop) handled as Ctrl-C while a command
    runs: its output keeps what it wrote and its lock is released (killed outright, a run
    left an empty folder holding a stale lock file). Main thread only; the previous handler
    comes back afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    owner = os.getpid()

    def stop(signum: int, frame: object) -> None:
        if os.getpid() != owner:  # a forked worker: stopped as it would have been
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class _QuietWhenClosed:
    """A stdout or stderr whose reader may go away: a ``BrokenPipeError`` on writing or
    flushing points the file descriptor at ``/dev/null`` (so nothing, not even Python's flush
    at exit, raises again) and the text is dropped. Everything else is the wrapped stream's."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream

    def _silence(self) -> None:
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, self._stream.fileno())
        finally:
            os.close(devnull)

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            self._silence()
            return len(text)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._silence()
            with contextlib.suppress(OSError):  # what was buffered now goes to /dev/null
                self._stream.flush()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


@contextlib.contextmanager
def _closed_stdout_is_quiet() -> Iterator[None]:
    """Run the block with a closed stdout dropping what is printed instead of raising: the
    error used to end a finished run inside :func:`~sq_mitsuba.outputs.all_or_nothing`,
    which then deleted its files; a block-buffered stdout failed at exit instead (code 120).
    The block's prints are flushed before it ends, so a failure to show them surfaces here."""
    stream = sys.stdout
    if isinstance(stream, _QuietWhenClosed) or not isinstance(stream, io.TextIOBase):
        yield  # wrapped already (main within main), no stdout, or an unusual one: as it is
        return
    sys.stdout = _QuietWhenClosed(stream)
    try:
        yield
    finally:
        try:
            sys.stdout.flush()  # a closed pipe is silenced by the wrapper itself
        except ValueError:  # closed by the command
            pass
        except OSError as error:  # another failure to write (a full disk): not to be lost
            sys.stdout = stream
            print(f"sq-mitsuba: error: the standard output could not be written: {error}",
                  file=sys.stderr)
            raise SystemExit(EXIT_ERROR) from None
        sys.stdout = stream


@contextlib.contextmanager
def _closed_stderr_is_quiet() -> Iterator[None]:
    """Run the block with a closed stderr dropping what is written (progress bars, warnings)
    instead of raising: ``sq-mitsuba eval ... 2>&1 | head -1`` used to end the run at its
    next progress line and delete its files, with no message (stderr was the closed pipe)."""
    stream = sys.stderr
    if isinstance(stream, _QuietWhenClosed) or not isinstance(stream, io.TextIOBase):
        yield
        return
    sys.stderr = _QuietWhenClosed(stream)
    try:
        yield
    finally:
        with contextlib.suppress(OSError, ValueError):  # nowhere left to say it
            sys.stderr.flush()
        sys.stderr = stream


def _parse(parser: argparse.ArgumentParser, argv: list[str]) -> argparse.Namespace:
    """``parser.parse_args(argv)``, but an unknown option is reported by the (sub)command
    it was given to (``sq-mitsuba eval: error: unrecognized arguments: --refien (see
    sq-mitsuba eval --help)``), not by the top-level parser, whose help does not list it."""
    args, extra = parser.parse_known_args(argv)
    if extra:
        owner = parser
        for word in argv:  # the deepest subcommand named in argv
            choices = next((action.choices for action in owner._actions
                            if isinstance(action, argparse._SubParsersAction)), {})
            if word in choices:
                owner = choices[word]
        owner.error(f"unrecognized arguments: {' '.join(extra)}")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``sq-mitsuba argv``; returns the exit code (see the module docstring for errors)."""
    with _terminate_as_interrupt(), _closed_stderr_is_quiet(), _closed_stdout_is_quiet():
        return _main(argv)


def _main(argv: Sequence[str] | None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    # The command is the first word after the global options (only --traceback).
    first = next((i for i, word in enumerate(argv) if word != TRACEBACK_FLAG), len(argv))
    command = argv[first] if first < len(argv) and argv[first] in command_names() else None
    args = _parse(build_parser(command, listing=True), argv)
    if not hasattr(args, "func"):  # a listed-only command was reached some other way
        args = _parse(build_parser(args.command), argv)
    show_traceback = args.traceback or traceback_from_environment()
    from sq_mitsuba.outputs import all_or_nothing

    kind = ALL_OR_NOTHING.get(args.command)
    try:
        check_variant_environment()  # a misspelled variant: before any work, not mid-render
        launch_ranks()  # and a malformed RANK, WORLD_SIZE, LOCAL_RANK or LOCAL_WORLD_SIZE
        with warnings.catch_warnings(), all_or_nothing(
                getattr(args, "out", None) if kind else None, kind == "file",
                keep=KEEP_ON_FAILURE.get(args.command, ()),
                outputs=OUTPUT_NAMES.get(args.command)):
            if not show_traceback:  # warnings as one line each (--traceback: Python's own)
                warnings.showwarning = _warning_printer(args.command)
            return int(args.func(args) or 0)
    except (KeyboardInterrupt, Exception) as error:
        if interrupted(error):  # Ctrl-C, also when Dr.Jit disguised it: one line, exit 130
            if show_traceback:
                traceback.print_exc()
            hint = _resume_hint(args)
            if _speaker(args.command) == f"sq-mitsuba {args.command}":  # rank 0 for them all
                print(f"sq-mitsuba {args.command}: interrupted" + (f" ({hint})" if hint else ""),
                      file=sys.stderr)
            return EXIT_INTERRUPTED
        if show_traceback:
            raise
        if isinstance(error, CLIError | ValueError | OSError | BackendError):  # bad input
            print(f"{_speaker(args.command)}: error: {_one_line(error)}", file=sys.stderr)
            return EXIT_ERROR
        # A bug: still one line, but named as such, and how to see more.
        name, detail = type(error).__name__, _one_line(error)
        what = name if detail == name else f"{name}: {detail}"
        print(f"{_speaker(args.command)}: internal error: {what} ({TRACEBACK_HINT})",
              file=sys.stderr)
        return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(main())
