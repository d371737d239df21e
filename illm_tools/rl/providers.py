"""Which target provider serves a bonus: `TARGET_PROVIDERS`, keyed by the kind of targets a bonus
declares (`IntrinsicBonus.target_kind`, a `TargetProvider` protocol of the layer below), so the
bonus names no trainer code and the import contract sees the seam (this module imports the kinds;
nothing below imports it).

Whoever assembles a run (`illm_tools.rl.run.make_provider`) looks the bonus's kind up here, builds
the provider with the class's `for_run(cfg, cache, builder, *, num_actions, live, shuffle_seed)`
and hands it to the trainer, which hands it to the bonus (`use_provider`). Built in: the targets of
the run's language tasks (`TargetProvider` itself: `CachedTargets`) and ELLM's goals
(`GoalProvider`: `GoalTargets`). A plug-in bonus that reads something else declares a kind of its
own and registers its provider under the kind's name (`kind_name`: "module:Qualname"), by code
(`TARGET_PROVIDERS.register`) or through the `illm.target_providers` entry point of its package.
"""

from __future__ import annotations

from illm_tools.errors import UsageError
from illm_tools.intrinsic.base import TargetProvider
from illm_tools.intrinsic.ellm import GoalProvider
from illm_tools.registry import Registry
from illm_tools.rl.targets import CachedTargets, GoalTargets


def _provider_problem(cls) -> str | None:
    """What keeps a class from being a target provider a run can build."""
    if not isinstance(cls, type):
        return "is not a class"
    missing = [m for m in ("for_run", "targets", "stats") if not callable(getattr(cls, m, None))]
    return f"has no {', '.join(missing)} (a TargetProvider with a classmethod for_run)" if missing else None


TARGET_PROVIDERS: Registry = Registry("target provider", "illm.target_providers", check=_provider_problem)
"""The kind of targets a bonus reads (`kind_name` of its `target_kind`) -> the provider class that
serves it; installed packages add theirs through `illm.target_providers` entry points."""


def kind_name(kind: type) -> str:
    """The registry's name of a kind of targets: "module:Qualname" of its protocol."""
    return f"{kind.__module__}:{kind.__qualname__}"


def provider_class(bonus: type) -> type:
    """The provider class serving the targets a bonus class reads (its `target_kind`); one line
    naming the kind where no provider is registered for it."""
    name = kind_name(bonus.target_kind)
    if name not in TARGET_PROVIDERS:
        raise UsageError(f"no target provider serves {name}, the targets {bonus.__name__} reads: register one in "
                         "illm_tools.rl.providers.TARGET_PROVIDERS, or under the illm.target_providers entry point")
    return TARGET_PROVIDERS.load(name)


TARGET_PROVIDERS.register(kind_name(TargetProvider), CachedTargets)
TARGET_PROVIDERS.register(kind_name(GoalProvider), GoalTargets)
