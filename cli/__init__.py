"""The `illm` command line (`cli.main`).

Importing the commands takes a third of a second or more (Typer, every command's options). A
Ctrl-C in that time would end in Python's traceback from inside the import, before any command's
one-line error handling exists; so the `illm` script, and only it, ends such an interrupt as every
other: one line, exit code 130 (nothing has been written yet). `cli.main.main` puts Python's own
handler back before the command runs.
"""

import os
import signal
import sys


def _interrupted_while_starting(signum, frame) -> None:
    os.write(2, b"interrupted: KeyboardInterrupt\n")  # unbuffered: nothing is flushed on the way out
    os._exit(130)


if os.path.basename(sys.argv[0] if sys.argv else "") == "illm" \
        and signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not where SIGINT is ignored
    signal.signal(signal.SIGINT, _interrupted_while_starting)
