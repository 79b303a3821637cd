"""One line per user error at every command line, the traceback only with ``--debug``.

A user error is a bad file or folder (``OSError``: missing, unreadable, not a directory) or
a value the code refuses (``ValueError``, which :class:`ScenarioFormatError` and the
argument checks raise, naming the file or the argument and what was expected).
:func:`user_errors` prints such an error as ``<prog>: error: <message>`` on stderr and
exits with status 2, as argparse does for a bad flag; ``--debug`` (declared by
:func:`add_debug_flag`) re-raises it instead, with its traceback. Ctrl-C is one line and
status 130, saying what the command kept on disk; SIGTERM the same, status 143. Any
other exception is a bug and keeps its traceback. The console scripts (``riskflow-data``,
``riskflow-eval``, ``riskflow-stress``, ``riskflow-train``) run their work inside it, and
so do the examples and benchmarks that read files or planner specs (:func:`run_script`,
:func:`policies.dataclass_cli.run_main`).
"""

from __future__ import annotations

import argparse
import importlib.util
import re
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, NoReturn

from riskflow_env.untrusted import error_text

USER_ERRORS = (OSError, ValueError)
MAX_LINE = 1000  # [characters] of an error message printed


class CommandLineParser(argparse.ArgumentParser):
    """argparse's parser with a short usage error: ``usage: <prog> [options] ...`` and the
    error line, where argparse prints the whole usage first (over 30 lines for a command
    with 40 options); ``--help`` still lists every option."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"usage: {self.prog} [options] (--help lists them)\n"
                     f"{self.prog}: error: {message}\n")  # fmt: skip


_DEFAULT_IN_WORDS = re.compile(r"[;,]\s+default:?\s+")  # "...; default: the shipped bank"


class DefaultsHelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """argparse's help with each option's default, and ``(required)`` for an option that
    must be given, where argparse shows ``(default: None)``.

    A help text that ends by saying its default in words (``...; default: the shipped
    bank``) shows it once, as ``(default: the shipped bank)``, where argparse would add
    ``(default: None)`` (or ``()``) after it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        help_text = action.help or ""
        # required, or only until a --recipe gives it; a positional is required anyway
        if (action.required or getattr(action, "recipe_may_give", False)) and action.option_strings:
            return help_text if "(required" in help_text else f"{help_text} (required)"
        in_words = _DEFAULT_IN_WORDS.search(help_text)
        empty = isinstance(action.default, (tuple, list)) and not action.default
        unset = action.default is None or empty  # nothing to show
        if in_words and unset and action.option_strings:
            return f"{help_text[: in_words.start()]} (default: {help_text[in_words.end() :]})"
        return super()._get_help_string(action)


def add_debug_flag(parser: argparse.ArgumentParser) -> None:
    """Declare ``--debug`` on ``parser``."""
    parser.add_argument(
        "--debug",
        action="store_true",
        help="show the Python traceback of an error instead of one line",
    )


def debug_requested(argv: Sequence[str]) -> bool:
    """Whether ``argv`` asks for ``--debug`` (argparse's abbreviations included), for a
    command whose parser does not hand the flag back."""
    flag = argparse.ArgumentParser(add_help=False)
    add_debug_flag(flag)
    return flag.parse_known_args(list(argv))[0].debug


def message(error: BaseException) -> str:
    """The one-line text of ``error``: its message (no longer than ``MAX_LINE``), prefixed
    with its type for an ``OSError`` the system raised (``PermissionError: [Errno 13] ...``
    says what went wrong; the library's own messages say it in words)."""
    text = error_text(error, limit=MAX_LINE)
    if not (isinstance(error, OSError) and error.errno is not None):
        text = text.split(": ", 1)[-1]
    return " ".join(text.split())  # one line


INTERRUPTED = 130  # the exit status of a command stopped by Ctrl-C (128 + SIGINT)


def missing_extra(prog: str, extra: str, module: str) -> str:
    """The one line of a script that needs ``module``, of the ``extra`` extra, without it."""
    return f"{prog}: error: needs the {extra} extra ({module} is not installed): " + (
        f"pip install -e '.[{extra}]'"
    )


def require_extra(prog: str, extra: str, module: str) -> None:
    """Exit with :func:`missing_extra`'s line (status 1) unless ``module`` can be imported,
    before a script sets anything up."""
    try:
        found = importlib.util.find_spec(module) is not None  # a.b imports a first
    except ModuleNotFoundError:
        found = False
    if not found:
        raise SystemExit(missing_extra(prog, extra, module))


def interrupt_of(error: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C behind ``error``: itself, or the ``KeyboardInterrupt`` that one or more
    ``SystemError`` surfaced around (Ctrl-C inside a compiled numba function); None for
    any other error."""
    while isinstance(error, SystemError):  # numba may wrap it more than once
        error = error.__cause__ or error.__context__
    return error if isinstance(error, KeyboardInterrupt) else None


@contextmanager
def user_errors(prog: str, debug: bool = False, kept: str = "") -> Iterator[None]:
    """Run the body; a user error (``USER_ERRORS``) becomes one line on stderr and exit
    status 2, or propagates with its traceback when ``debug``. Ctrl-C
    (``KeyboardInterrupt``) and SIGTERM (what a scheduler or ``kill`` sends) become one
    line too, ``<prog>: interrupted`` with the interrupt's own message (what was done) and
    ``kept`` (what is on disk and how to go on), and the shell's status for the signal:
    130 for Ctrl-C, 143 for SIGTERM. SIGTERM raises ``KeyboardInterrupt`` in the main
    thread while the body runs, so the body keeps what is finished as on Ctrl-C; a SIGTERM
    that the process was started to ignore stays ignored."""
    sigterm = _SigTerm()
    try:
        yield
    except USER_ERRORS as error:
        if debug:
            raise
        print(f"{prog}: error: {message(error)} (--debug shows the traceback)", file=sys.stderr)
        raise SystemExit(2) from None
    except (KeyboardInterrupt, SystemError) as error:
        interrupt = interrupt_of(error)
        if debug or interrupt is None:
            raise
        said = "; ".join(part for part in (str(interrupt), kept) if part)
        print(f"\n{prog}: interrupted" + (f": {said}" if said else ""), file=sys.stderr)
        raise SystemExit(128 + signal.SIGTERM if sigterm.received else INTERRUPTED) from None
    finally:
        sigterm.restore()


class _SigTerm:
    """SIGTERM raising ``KeyboardInterrupt`` in the main thread until :meth:`restore`;
    ``received`` says whether it came. Nothing is installed outside the main thread
    (signals cannot be handled there) or when SIGTERM is ignored."""

    def __init__(self) -> None:
        self.received, self.installed = False, False
        if threading.current_thread() is not threading.main_thread():
            return
        if signal.getsignal(signal.SIGTERM) is signal.SIG_IGN:
            return
        self.previous = signal.signal(signal.SIGTERM, self._handle)
        self.installed = True

    def _handle(self, signum: int, frame: Any) -> None:
        self.received = True
        raise KeyboardInterrupt

    def restore(self) -> None:
        if self.installed:
            signal.signal(signal.SIGTERM, self.previous)
            self.installed = False


def run_script(prog: str, main: Callable[[], Any], argv: Sequence[str] | None = None) -> None:
    """The ``__main__`` of an example or a benchmark: ``main()`` inside :func:`user_errors`,
    with ``--debug`` read from ``argv`` (``sys.argv[1:]`` if None). ``main`` parses the
    command line itself, with ``--debug`` declared (``parse_dataclass(..., debug=True)``)."""
    with user_errors(prog, debug_requested(sys.argv[1:] if argv is None else argv)):
        main()
