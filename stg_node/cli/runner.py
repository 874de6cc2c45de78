"""How every stg-* command starts and ends: exit codes, Ctrl-C/SIGTERM, logging, error messages.

Every entry point is ``main(argv=None) -> int`` around :func:`run_main`, so that the
convention below holds for all of them, today's and future ones (docs/CLI.md)::

    def main(argv=None) -> int:
        return run_main(build_parser(), run, argv)      # run(args) -> int | None

Exit codes:

====  ====================================================================================
0     done; for commands that run until stopped (stg-broker, stg-topic), also a stop by
      Ctrl-C or SIGTERM, their normal end
1     the work failed: a runtime error, a file that cannot be read or holds bad data, an
      address in use, a broker already running, a missing key
2     bad usage, found before any work starts: argparse errors, an invalid option value or
      combination (raise :class:`UsageError`), a bad log level
130   a job that ends by itself was interrupted (Ctrl-C or SIGTERM) before it finished
====  ====================================================================================

Expected failures (``OSError``, ``ValueError``, :class:`CommandFailed`, and what a command
adds with ``expected=``) are reported as one line, ``PROG: error: MESSAGE``, on stderr,
the form argparse uses for usage errors; their traceback is logged at DEBUG
(``STG_LOG_LEVEL=DEBUG``). Anything else is a bug: message and traceback, exit 1.
"""

from __future__ import annotations

import argparse
import logging
import sys
import traceback
from collections.abc import Callable, Sequence

from stg_node.logs import configure_logging
from stg_node.signals import interrupt_on_signals

log = logging.getLogger(__name__)

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as a shell reports a job ended by Ctrl-C


class UsageError(Exception):
    """The command line is wrong (an invalid option value or combination): usage, message, exit 2."""


class CommandFailed(Exception):
    """The work failed for a reason the user can act on: the message alone, exit 1."""


#: Failures that are the user's situation rather than our bug: one line, exit 1.
EXPECTED_ERRORS: tuple[type[BaseException], ...] = (CommandFailed, OSError, ValueError)


def add_log_level_option(parser: argparse.ArgumentParser) -> None:
    """``--log-level``: read by :func:`run_main` before the command runs."""
    parser.add_argument(
        "--log-level", metavar="LEVEL", help="DEBUG, INFO, WARNING, ... (default $STG_LOG_LEVEL or INFO)"
    )


def _exit_code(exc: SystemExit) -> int:
    """The exit status ``sys.exit(code)`` would give (argparse: 0 after --help, 2 on errors)."""
    if exc.code is None:
        return EXIT_OK
    if isinstance(exc.code, int):
        return exc.code
    print(exc.code, file=sys.stderr)
    return EXIT_FAILED


def run_main(
    parser: argparse.ArgumentParser,
    command: Callable[[argparse.Namespace], int | None],
    argv: Sequence[str] | None = None,
    *,
    stop_is_success: bool = False,
    expected: tuple[type[BaseException], ...] = (),
) -> int:
    """Parse ``argv``, set up logging, run ``command(args)`` and map its end to an exit code.

    ``stop_is_success``: the command runs until stopped, so Ctrl-C / SIGTERM is its normal
    end (exit 0) rather than an interruption (130). ``expected``: further exception
    types that are failures to report in one line rather than bugs. See the module
    docstring for the codes.
    """
    prog = parser.prog
    with interrupt_on_signals():  # SIGINT too: a background start inherits it ignored
        try:
            args = parser.parse_args(argv)
            try:
                configure_logging(getattr(args, "log_level", None))
            except ValueError as exc:
                raise UsageError(str(exc)) from exc
            code = command(args)
            return EXIT_OK if code is None else int(code)
        except SystemExit as exc:
            return _exit_code(exc)
        except UsageError as exc:
            parser.print_usage(sys.stderr)
            print(f"{prog}: error: {exc}", file=sys.stderr)
            return EXIT_USAGE
        except KeyboardInterrupt:
            if stop_is_success:
                return EXIT_OK
            print(f"{prog}: interrupted", file=sys.stderr)
            return EXIT_INTERRUPTED
        except (*EXPECTED_ERRORS, *expected) as exc:
            log.debug("%s failed", prog, exc_info=True)
            print(f"{prog}: error: {exc}", file=sys.stderr)
            return EXIT_FAILED
        except Exception as exc:
            print(
                f"{prog}: unexpected error (a bug; please report it with this output): {exc!r}",
                file=sys.stderr,
            )
            traceback.print_exc(file=sys.stderr)
            return EXIT_FAILED
