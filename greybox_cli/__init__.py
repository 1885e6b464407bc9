"""Entry point of the ``greybox`` command, light enough to catch an early Ctrl-C.

Importing greybox (numpy, scipy, python-control, matplotlib) takes about a
second. This module imports none of it before its ``try``, so Ctrl-C during
that second ends as it does later: "greybox: interrupted" on stderr and
exit code 130, not a traceback.
"""

import sys

__all__ = ["main"]


def main(argv=None) -> int:
    """Run :func:`greybox.cli.main` (same ``argv`` and exit codes), imported inside the try.

    Ctrl-C before ``greybox.cli.main`` takes over gives one line and exit code 130.
    """
    import signal

    hit = []

    def _interrupted(signum, frame):
        hit.append(signum)
        raise KeyboardInterrupt

    try:  # the interrupt remembered, not only raised: a library imported below can swallow
        # a KeyboardInterrupt in a broad except (seen once in CI: the demo then ran to exit 0)
        previous = signal.signal(signal.SIGINT, _interrupted)
    except ValueError:  # not the main thread: Python's own handler stays
        previous = None
    try:
        from greybox.cli import main as run

        if hit:
            raise KeyboardInterrupt
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
        return run(argv)
    except KeyboardInterrupt:
        print("greybox: interrupted", file=sys.stderr)
        return 130
