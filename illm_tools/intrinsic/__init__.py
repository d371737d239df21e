"""Intrinsic bonuses (one file each) behind the interface in `base.py`, plus shared normalisation."""

from illm_tools.intrinsic.base import (
    BonusRewards,
    IntrinsicBonus,
    StateRecord,
    TargetProvider,
    Targets,
)
from illm_tools.intrinsic.illm import ILLMBonus
from illm_tools.intrinsic.normalize import DiscountedReturnNormalizer, RunningMeanStd

__all__ = [
    "BonusRewards", "DiscountedReturnNormalizer", "ILLMBonus", "IntrinsicBonus",
    "RunningMeanStd", "StateRecord", "TargetProvider", "Targets",
]
