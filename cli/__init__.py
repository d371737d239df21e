"""The `illm` command line (`cli.main`).

Importing the commands takes a third of a second or more (Typer, every command's options). A
Ctrl-C in that time would end in Python's traceback from inside the import, before any command's
one-line error handling exists; so the `illm` script, and only it, ends such an interrupt as every
other: one line, exit code 130 (nothing has been written yet). `handled_from_here` puts Python's
own handler back once the command line's error handling is in place (`cli.main._OneLineErrors`).
Later, a command's first `import torch` runs with Ctrl-C held back until it ends
(`illm_tools.signals.defer_ctrl_c_in_imports`): interrupted inside it, the process could abort
(exit -6, `pybind11::error_already_set`) instead of ending in the one line.
Before this module runs, in CPython's own start (`site` and its `.pth` imports), a Ctrl-C is
CPython's: "Fatal Python error: init_import_site" and a traceback, whatever the program; no code of
a package runs early enough to hold it.
"""

import os
import signal
import sys


def _interrupted_while_starting(signum, frame) -> None:
    os.write(2, b"interrupted: KeyboardInterrupt\n")  # unbuffered: nothing is flushed on the way out
    os._exit(130)


if os.path.basename(sys.argv[0] if sys.argv else "") == "illm" \
        and signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not where SIGINT is ignored
    from illm_tools.signals import defer_ctrl_c_in_imports

    signal.signal(signal.SIGINT, _interrupted_while_starting)
    defer_ctrl_c_in_imports(["torch"])


def handled_from_here() -> None:
    """Put Python's own Ctrl-C handler back where the start-up's quiet exit is still in place: from
    here on an interrupt is the command's one-line error (or Typer's quiet exit 130 while it parses)."""
    if signal.getsignal(signal.SIGINT) is _interrupted_while_starting:
        signal.signal(signal.SIGINT, signal.default_int_handler)
