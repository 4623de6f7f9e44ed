"""``python -m liquid_splat ARGS`` and the ``liquid-splat`` console script: the
command-line tool, run in-process from the installed package (no Rust toolchain needed)."""

from __future__ import annotations

import sys
from typing import List, Optional

from . import _native


def main(argv: Optional[List[str]] = None) -> int:
    """Run the tool on ``argv`` (default ``sys.argv[1:]``) and return its exit code."""
    args = sys.argv[1:] if argv is None else list(argv)
    sys.stdout.flush()
    sys.stderr.flush()
    return int(_native.cli(args))


if __name__ == "__main__":
    sys.exit(main())
