"""``python -m liquid_splat ARGS`` and the ``liquid-splat`` console script: the
command-line tool, run in-process from the installed package (no Rust toolchain needed)."""

from __future__ import annotations

import os
import signal
import sys
import threading
from typing import List, Optional

from . import _native


def main(argv: Optional[List[str]] = None) -> int:
    """Run the tool on ``argv`` (default ``sys.argv[1:]``) and return its exit code.

    This is the console script's entry point, and it acts as one: it gives SIGINT and
    SIGPIPE their default actions, since the tool runs without the interpreter in between:
    Ctrl-C ends it as it ends the native binary, and a closed stdout (``liquid-splat ... |
    head -1``) ends it quietly. An argument that is not UTF-8 exits 2 with a message. Code
    that runs the tool inside its own process calls :func:`liquid_splat.cli`, which leaves
    signal handling alone."""
    args = sys.argv[1:] if argv is None else list(argv)
    for i, a in enumerate(args, 1):
        try:
            a.encode("utf-8")
        except UnicodeEncodeError:
            print(
                f"error: argument {i} is not valid UTF-8: {os.fsencode(a)!r} "
                "(the tool takes UTF-8 arguments and file names)",
                file=sys.stderr,
            )
            return 2
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        if hasattr(signal, "SIGPIPE"):
            signal.signal(signal.SIGPIPE, signal.SIG_DFL)
    sys.stdout.flush()
    sys.stderr.flush()
    return int(_native.cli(args))


if __name__ == "__main__":
    sys.exit(main())
