"""Ctrl-C held back where raising it would do harm, and let through once that is over.

- `ctrl_c_deferred()`: a `with` block in which SIGINT neither interrupts nor is lost. The worker's
  spawn uses it (`illm_tools.rl.live`: one landing in the middle of the spawn would leave the worker
  half started), and so does torch's first import in the `illm` command (below).
- `defer_ctrl_c_in_imports(names)`: those modules' first import runs inside `ctrl_c_deferred`.
  `import torch` runs Python code called from torch's C++ (pybind11): a KeyboardInterrupt raised
  there cannot unwind through it, and the process aborts (`terminate called after throwing an
  instance of 'pybind11::error_already_set'`, exit -6) with no one-line error and its worker left
  behind. Here 4 of 700 `import torch` interrupted at a random moment ended that way (and 5 more
  ended 1), and so did a fresh-clone CI run's Ctrl-C test
  (docs/results/measured/ctrl-c-torch-import.txt); with the import deferred, the Ctrl-C arrives as
  the import ends, and the command reports it as any other. Hand-written: the standard library offers no
  "around this import" hook short of a finder whose loader wraps the real one's `exec_module`.
"""

from __future__ import annotations

import importlib.abc
import signal
import sys
import threading
from collections.abc import Iterable
from contextlib import contextmanager


@contextmanager
def ctrl_c_deferred():
    """SIGINT blocked in this thread and, in the main thread, this process's handler replaced by one
    that only records it (a signal the OS hands to another thread still runs the Python handler in
    the main thread). On the way out the handler is put back and a Ctrl-C that came meanwhile
    reaches it, once: none is lost. Only the main thread may set handlers; elsewhere only the block
    applies. Threads started inside inherit the block and leave SIGINT to the main thread."""
    came: list[int] = []
    handler = signal.getsignal(signal.SIGINT) if threading.current_thread() is threading.main_thread() else None
    if handler is not None:
        signal.signal(signal.SIGINT, lambda signum, frame: came.append(signum))
    held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)
        if handler is not None:
            signal.signal(signal.SIGINT, handler)
            if came and callable(handler):
                handler(signal.SIGINT, None)
            elif came and handler == signal.SIG_DFL:
                signal.raise_signal(signal.SIGINT)


class _Deferred(importlib.abc.Loader):
    """A module's own loader, its `exec_module` run inside `ctrl_c_deferred`; everything else (the
    resource reader, `get_filename`, ...) is the loader's own."""

    def __init__(self, loader):
        self._loader = loader

    def create_module(self, spec):
        return self._loader.create_module(spec)

    def exec_module(self, module) -> None:
        with ctrl_c_deferred():
            self._loader.exec_module(module)

    def __getattr__(self, name):
        return getattr(self._loader, name)


class _DeferredImports(importlib.abc.MetaPathFinder):
    """Finds `names` as the finders after it would, with each one's loader wrapped in `_Deferred`;
    steps aside once all of them have been found."""

    def __init__(self, names: Iterable[str]):
        self.names = set(names)

    def find_spec(self, name, path, target=None):
        if name not in self.names:
            return None
        self.names.discard(name)
        if not self.names and self in sys.meta_path:
            sys.meta_path.remove(self)
        for finder in [f for f in sys.meta_path if f is not self and hasattr(f, "find_spec")]:
            spec = finder.find_spec(name, path, target)
            if spec is not None:
                if spec.loader is not None:
                    spec.loader = _Deferred(spec.loader)
                return spec
        return None


def defer_ctrl_c_in_imports(names: Iterable[str]) -> None:
    """The first import of each of `names` (top-level modules not imported yet) runs with Ctrl-C
    deferred until it ends (`ctrl_c_deferred`)."""
    pending = [name for name in names if name not in sys.modules]
    if pending:
        sys.meta_path.insert(0, _DeferredImports(pending))
