"""Intrinsic bonuses (one file each) behind the interface in `base.py`, the method registry
(`registry.py`), and shared normalisation.

Names are imported on first use (PEP 562), so `illm_tools.intrinsic.registry` stays light: the
command line lists the methods without importing torch.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "BonusContext": "base", "BonusRewards": "base", "IntrinsicBonus": "base", "NoBonus": "base",
    "StateRecord": "base", "TargetProvider": "base", "Targets": "base",
    "ILLMBonus": "illm", "ILLMConfig": "illm", "RNDBonus": "rnd", "RNDConfig": "rnd",
    "NGUBonus": "ngu", "NGUConfig": "ngu", "APTBonus": "apt", "APTConfig": "apt", "ELLMBonus": "ellm",
    "ELLMConfig": "ellm",
    "DiscountedReturnNormalizer": "normalize", "RunningMeanStd": "normalize",
    "METHODS": "registry", "Method": "registry", "get_method": "registry", "register": "registry",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
