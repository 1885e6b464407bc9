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

    previous = None
    try:  # the interrupt remembered, not only raised: a library imported below can swallow
        # the KeyboardInterrupt in a broad except (seen in CI: the demo then ran to exit 0), or
        # a C extension's initialisation can turn it into "ImportError: initialization failed"
        if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:  # a background job's
            previous = signal.signal(signal.SIGINT, _interrupted)  # ignored SIGINT stays so
    except ValueError:  # not the main thread: Python's own handler stays
        pass
    try:
        try:
            from greybox.cli import main as run
        except Exception:
            if hit:  # an exception raised from the interrupt
                raise KeyboardInterrupt from None
            raise
        if hit:
            raise KeyboardInterrupt
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
        return run(argv)
    except KeyboardInterrupt:
        print("greybox: interrupted", file=sys.stderr)
        return 130
