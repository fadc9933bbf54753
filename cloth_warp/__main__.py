"""`python -m cloth_warp` and the `cloth-warp` script: the cloth-warp command."""

import os
import sys


def command() -> int:
    """The cloth-warp command, its modules loaded here: a Ctrl-C while they load, before
    :func:`cloth_warp.cli.main` has its handlers, exits 130 without a traceback as one later does. (Loaded by the
    script's own import, such a Ctrl-C left a traceback and exit -2: test_ctrl_c_at_any_moment[0.3] on a loaded
    machine, 2026-12-01.)"""
    try:
        from .cli import main
    except KeyboardInterrupt:  # nothing is open yet
        import signal

        signal.signal(signal.SIGINT, signal.SIG_IGN)
        sys.stderr.write("cloth-warp: interrupted\n")
        sys.stderr.flush()
        os._exit(130)
    return main()


if __name__ == "__main__":
    sys.exit(command())
