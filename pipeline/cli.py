"""The ``mushroom-pose`` command line: one subcommand per job, flags mapped onto config dataclasses."""

from __future__ import annotations

import argparse
import atexit
import errno
import os
import signal
import sys
import threading

from pipeline.commands import (average, calibrate, cameras, demo, detect, evaluate, live, record, recover, replay,
                               report, synth, track, train)
from common.distributed import RayUnavailable
from pipeline.commands.common import CliError, CommandFailed
from pipeline.process import reuse_freed_memory

COMMANDS = (synth, train, average, detect, evaluate, demo, cameras, record, recover, live, replay, calibrate, report,
            track)
"""The command modules (``NAME``, ``HELP``, ``add_arguments(parser)``, ``run(args)``), in ``--help``'s order."""


class OneLineErrorParser(argparse.ArgumentParser):
    """argparse with one-line errors: the message and where to look, no usage dump."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser(only: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser of every command; a parsed command runs as ``args.run(args)``. With ``only``, the
    other commands are listed but get no arguments: adding them is most of the parser's start-up."""
    parser = OneLineErrorParser(prog="mushroom-pose", description=__doc__)
    subparsers = parser.add_subparsers(dest="command", required=True, parser_class=OneLineErrorParser)
    for command in COMMANDS:
        command_parser = subparsers.add_parser(command.NAME, help=command.HELP)
        command_parser.set_defaults(run=command.run)
        if only is None or command.NAME in only:
            command.add_arguments(command_parser)
    return parser


DISK_ERRORS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EIO, errno.EFBIG}
"""Errors the user's input did not cause: the disk, not the command, failed."""


def main(argv: list[str] | None = None) -> int:
    """Run the command ``argv`` names; its exit status: 0 done, 2 bad input, 1 failed (a full disk, a
    failed write), 130 interrupted by Ctrl-C (a command stopped by SIGTERM returns 143 itself)."""
    interrupted: list[int] = []

    def on_interrupt(signum: int, frame) -> None:
        interrupted.append(signum)
        raise KeyboardInterrupt

    # Installed before numpy and each command's libraries load: C extensions turn a Ctrl-C during
    # their loading into other errors, such as ImportError("initialization failed"). An ignored
    # SIGINT (a background job) stays ignored.
    previous = signal.getsignal(signal.SIGINT) if threading.current_thread() is threading.main_thread() else None
    if previous in (signal.SIG_IGN, None):
        previous = None
    else:
        signal.signal(signal.SIGINT, on_interrupt)
    command = "mushroom-pose"
    try:
        argv = sys.argv[1:] if argv is None else argv
        args = build_parser(only=argv[:1]).parse_args(argv)
        command = f"mushroom-pose {args.command}"
        reuse_freed_memory()
        return args.run(args)
    except CliError as error:
        if not interrupted:
            print(f"{command}: error: {error}", file=sys.stderr)
            return 2
    except (CommandFailed, RayUnavailable) as error:
        if not interrupted:
            print(f"{command}: error: {error}", file=sys.stderr)
            return 1
    except OSError as error:
        if interrupted or error.errno not in DISK_ERRORS:
            raise
        where = f" ({error.filename})" if error.filename else ""
        print(f"{command}: error: {error.strerror}{where}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        pass
    except Exception:
        if not interrupted:
            raise
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
    print(f"{command}: interrupted", file=sys.stderr)
    return 130


class _ReaderMayLeave:
    """Standard output for a reader that may stop reading (``| head``): once the pipe breaks, the rest
    goes nowhere and the command still finishes and writes its files."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            self._gone()
            return len(text)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._gone()

    def _gone(self) -> None:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, self._stream.fileno())
        os.close(devnull)

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def console_main() -> None:
    """The ``mushroom-pose`` command. It ends without tearing the interpreter down: unloading torch,
    Open3D and scikit-learn takes about a second, longer than most of ``detect``. After a success the
    exit handlers run first (a Rerun stream flushes, Ray shuts down) once no worker thread is left;
    after an interrupt or a failure they are skipped: Open3D, interrupted while it loaded, would print
    a leak report and turn status 130 into 1, and a Rerun stream whose file writer failed (a full disk)
    would wait on it for ever."""
    sys.stdout = _ReaderMayLeave(sys.stdout)
    code = main()
    if code == 0:
        if any(thread.is_alive() and not thread.daemon for thread in threading.enumerate()
               if thread is not threading.main_thread()):
            sys.exit(code)  # the interpreter waits for them, then runs the exit handlers
        atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    console_main()
