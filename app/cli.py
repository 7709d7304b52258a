"""The `photopft` command line."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from pathlib import Path

from core import __version__
from app.errors import UserError
from core.io.outputs import OutputError, clear_stop, request_stop, requested_stop
from core.io.session import SessionError

# A verb imports its work when it runs: app/cli.py builds every verb's parser at start-up (docs/architecture.md)

log = logging.getLogger("photopft")

class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread like Ctrl-C so that every `finally` cleans up."""


def _stop(signum, frame) -> None:
    """SIGTERM and SIGINT: raise in the main thread, and tell every output not to be put in place."""
    reason = Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()
    request_stop(reason)
    raise reason


def _quiet_stop_in_callbacks(unraisable) -> None:
    """A stop raised inside a C callback is swallowed there (and acted on when the output would be
    put in place): no traceback for it; anything else is reported as Python would."""
    if not isinstance(unraisable.exc_value, KeyboardInterrupt):
        sys.__unraisablehook__(unraisable)


def _bench_verb():
    """The `bench` verb's adder from the source checkout this application runs from (benchmarks/, beside
    app/), or None: an installed or bundled application ships without the benchmarks."""
    checkout = Path(__file__).resolve().parents[1]
    if not (checkout / "benchmarks" / "cli.py").is_file():
        return None
    if str(checkout) not in sys.path:
        sys.path.insert(0, str(checkout))
    from benchmarks.cli import add_bench

    return add_bench


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="photopft", description="Non-contact lung function testing by "
                                     "near-light photometric stereo. Every verb has --help.")
    parser.add_argument("--version", action="version", version=f"photopft {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log details to standard error")
    sub = parser.add_subparsers(dest="verb", metavar="VERB")
    from app.commands.demo import add_demo
    from app.commands.session import add_info, add_recover, add_simulate, add_validate, describe_session, run_simulate

    add_simulate(sub)
    add_info(sub)
    add_validate(sub)
    add_recover(sub)
    from app.commands.reconstruction import add_calibrate, add_process

    from app.commands.analyze import add_analyze
    from app.commands.batch import add_batch
    from app.commands.emulate import add_emulate
    from app.commands.record import add_record
    from app.commands.records import add_records_verbs
    from app.commands.review import add_review_verbs
    from app.gui.app import add_gui

    add_calibrate(sub)
    add_process(sub)
    add_analyze(sub)
    add_batch(sub)
    add_bench = _bench_verb()
    if add_bench is not None:
        add_bench(sub)
    add_emulate(sub)
    add_record(sub)
    add_records_verbs(sub)
    add_review_verbs(sub)
    add_gui(sub)
    add_demo(sub, run_simulate, describe_session)
    return parser


def _one_line_naming_the_input(exc: Exception, args: argparse.Namespace) -> str:
    """The error in one line that names the file: a read that failed deep in a library (HDF5's
    words for a damaged file) is prefixed with the command's input; a complaint about an option's
    value (it starts with the option) is not, nor an output that could not be written (OutputError
    names it: a bench's scratch file is no input of the command)."""
    lines = str(exc).splitlines()
    message = lines[0] if lines else type(exc).__name__
    if isinstance(exc, OutputError):
        return message
    named = [str(v) for k, v in vars(args).items() if isinstance(v, Path) and k != "output"]
    about_an_option = message.startswith("--")
    if named and not about_an_option and not any(name in message or Path(name).name in message for name in named):
        message = f"{named[0]}: {message}"
    return message


def main(argv: list[str] | None = None) -> int:
    from app.auth import forget

    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "run", None):
        parser.print_help()
        return 2
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = {sig: signal.signal(sig, _stop) for sig in (signal.SIGTERM, signal.SIGINT)} if in_main_thread else {}
    clear_stop()
    forget()  # who acts is named by this command (--user, $PHOTOPFT_USER) and proven by it
    sys.unraisablehook = _quiet_stop_in_callbacks
    try:
        return int(args.run(args) or 0)
    except KeyboardInterrupt as exc:
        return _stopped(args, exc)
    except Exception as exc:
        if (stop := requested_stop()) is not None:
            return _stopped(args, stop)
        if not isinstance(exc, (UserError, SessionError, OutputError, OSError)):
            raise
        print(f"photopft {args.verb}: error: {_one_line_naming_the_input(exc, args)}", file=sys.stderr)
        return 2
    finally:
        forget()  # a password given to this command proves nothing to the next
        _restore_handlers(previous)
        clear_stop()  # answered: a caller in the same process (a test, a script) goes on unstopped
        sys.unraisablehook = sys.__unraisablehook__


def _stopped(args: argparse.Namespace, reason: BaseException) -> int:
    """A stop asked for by a signal, whatever it broke on its way out: a library whose work it cut
    short may fail in its own words after it (numba, stopped while it compiled, failing to cache
    the kernel), and that failure is the stop's, not the input's."""
    if isinstance(reason, Terminated):
        print(f"photopft {args.verb}: terminated; nothing half-written was left", file=sys.stderr)
        return 143
    print(f"photopft {args.verb}: interrupted; nothing half-written was left", file=sys.stderr)
    return 130


def _restore_handlers(previous: dict) -> None:
    """The handlers the command found, put back. `signal.signal` runs a signal still pending: a
    second Ctrl-C while the first is answered is the same request, not a new traceback."""
    for sig, handler in previous.items():
        try:
            signal.signal(sig, handler)
        except KeyboardInterrupt:
            pass


if __name__ == "__main__":
    sys.exit(main())
