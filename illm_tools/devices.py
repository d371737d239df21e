"""Where a stage's torch work runs: `--device cpu|cuda|cuda:N|auto`, checked in one place.

`check_device` refuses a malformed name when a config is built; `resolve_device` turns auto into
the machine's accelerator and refuses, in one line, a CUDA device this machine does not have
(rather than a CUDA error deep in a model's load). Under several processes (`accelerate launch`)
cuda and auto name each process's own GPU (`state`: accelerate's `PartialState`).
"""

from __future__ import annotations

from illm_tools.errors import UsageError

CHOICES = "cpu, cuda, cuda:N or auto"


def check_device(device: str, flag: str = "--device") -> None:
    """Refuse a device name that is not cpu, cuda, cuda:N or auto."""
    index = device[5:] if isinstance(device, str) and device.startswith("cuda:") else None
    if not (device in ("cpu", "cuda", "auto") or (index is not None and index.isdigit())):
        raise UsageError(f"{flag} must be {CHOICES}, got {device!r}")


def resolve_device(device: str, state=None, flag: str = "--device") -> str:
    """The torch device: `device`, or for auto the process's accelerator (cuda when there is one,
    else cpu). A CUDA device the machine lacks is refused in one line."""
    import torch

    check_device(device, flag)
    if state is not None and device in ("cuda", "auto") and state.device.type == "cuda":
        return str(state.device)
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda"):
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        index = int(device[5:]) if ":" in device else 0
        if index >= count:
            have = f"{count} CUDA device{'s' * (count != 1)}" if count else "no CUDA device"
            raise UsageError(f"{flag} {device}: this machine has {have} (torch {torch.__version__}); "
                             "use --device cpu, or auto to take a GPU where there is one")
    return device
