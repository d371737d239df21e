"""Training methods by name: `illm train --method NAME` -> an intrinsic bonus class and its config.

Owns `METHODS` (the registry: a live name -> `Method` mapping, which `TrainConfig` validates
against and `--method`'s help lists), `register` (adds a method; the trainer needs no change),
`get_method` (a name, or one line saying which exist) and the conversion of a run's settings into
a bonus's config dataclass.

A method is a bonus class (an `IntrinsicBonus` subclass, given as the class or lazily as
"module:Class", as gymnasium's `entry_point`s are: `illm --help` never imports torch) plus whether
its reward is paid. `ppo` has no bonus. Built in:

  illm           iLLM heads + bonus (illm.py)
  illm-noreward  iLLM heads trained, no bonus paid (paper Table 3)
  ppo            no bonus
  rnd            Random Network Distillation (rnd.py); --bonus-preset rnd (advantage weights 2 / 1)
  ellm           ELLM (ellm.py): paid for transitions whose caption matches a goal the LLM suggested
                 (the cache's `goal` rows, `illm annotate --tasks goal`)
  ngu            Never Give Up (ngu.py): episodic kNN novelty x RND's life-long factor
  apt            Active Pre-Training (apt.py): particle-based entropy, kNN within the rollout
  illm-shuffled  iLLM, each state's targets another cached state's (a fixed permutation): the
                 control that tells the LLM's knowledge from curiosity

and, from the layer that owns the policy networks (which registers it when imported), `chibit`: no
bonus, the policy's torso the LLM's first blocks.

An installed package's `illm.methods` entry point whose name a registered method already has (a
built-in, or one registered by code, before or after the plug-ins are read) is refused: `get_method`,
the look-up of every command, answers that name with one line naming the plug-in and the built-in,
so a plug-in never silently loses its name to a built-in, nor takes a built-in's. The other names
work on.

A bonus's config is the run's own when its `config_class` names a TrainConfig field in `RUN_FIELD`
(iLLM's `ILLMConfig` is `TrainConfig.illm`: lambda_a, beta_hc, ... are top-level options of `illm
train`); otherwise its fields take `TrainConfig.bonus_options` (`illm train --bonus-option KEY=VALUE`)
or their defaults. An option a config does not have is refused.
"""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, Any

from illm_tools.errors import UsageError
from illm_tools.registry import Registry, load_class, load_reference

if TYPE_CHECKING:
    from illm_tools.intrinsic.base import BonusContext, IntrinsicBonus

__all__ = ["METHODS", "Method", "get_method", "method_help", "register"]


@dataclass(frozen=True)
class Method:
    """One `--method`: the bonus it trains with and whether that bonus's reward is paid."""

    name: str
    """What `--method` and `TrainConfig.method` say."""
    summary: str
    """A few words for `--help`."""
    entry_point: str | type | None = None
    """The `IntrinsicBonus` subclass, or "module:Class" imported on first use; None: no bonus."""
    pays_reward: bool = True
    """False: the bonus's models train, its reward is not paid (only advantages change)."""
    preset: str = "paper"
    """The `--bonus-preset` (bonus and advantage weights, `illm_tools.rl.config.BONUS_PRESETS`)
    `illm train` uses when none is given."""
    network: str | type | None = None
    """The policy network class (the class, or "module:Class" imported on first use: a
    `GridMissionNet` subclass), None: the suite's own (`illm_tools.envs.suite.Suite.network`). Its
    `Options` dataclass lists the `--network-option`s it takes."""
    target_shuffle: int | None = None
    """With `needs_targets`: None, each state's own LLM targets; an int, the seed of the fixed
    permutation that hands each state another cached state's targets instead (`CachedTargets`'s
    `shuffle_seed`, `illm_tools.rl.targets.ShuffledKeys`: the `illm-shuffled` control)."""

    @cached_property
    def network_class(self) -> type | None:
        """The method's own policy network class, loaded (None: it names none, and a run uses its
        suite's; the network layer checks the class)."""
        return load_reference(self.network) if isinstance(self.network, str) else self.network

    def network_options(self, options: Mapping[str, Any], network: type | None = None):
        """The options dataclass of `network` (default: the method's own) from `--network-option`
        values (None: it takes none; so does a method without a network of its own); unknown or
        ill-typed options are refused in one line."""
        cls = getattr(network or self.network_class, "Options", None)
        if cls is None:
            if options:
                raise UsageError(f"--method {self.name} takes no network option ({', '.join(options)})")
            return None
        allowed = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(options) - set(allowed))
        if unknown:
            raise UsageError(f"--method {self.name} has no network option {', '.join(unknown)}; it takes "
                             f"{', '.join(allowed)}")
        hints = typing.get_type_hints(cls)
        return cls(**{k: _typed(k, hints.get(k), v) for k, v in options.items()})

    @cached_property
    def bonus_class(self) -> type[IntrinsicBonus]:
        """The bonus class (`NoBonus` for a method without one)."""
        from illm_tools.intrinsic.base import IntrinsicBonus, NoBonus

        if self.entry_point is None:
            return NoBonus
        return load_class(self.entry_point, IntrinsicBonus, f"method {self.name}: bonus")

    @property
    def config_class(self) -> type | None:
        """The bonus's config dataclass (None: it has no settings)."""
        return self.bonus_class.config_class

    @property
    def needs_targets(self) -> bool:
        """Whether the run must supply LLM targets (an annotation cache)."""
        return self.bonus_class.needs_targets

    @property
    def policy_heads(self) -> bool:
        """Whether the policy network carries the iLLM heads f^a / f^hc."""
        return self.bonus_class.policy_heads

    @property
    def target_tasks(self) -> tuple[str, ...]:
        """The language tasks whose cache rows the run reads (with `needs_targets`)."""
        return tuple(self.bonus_class.target_tasks)

    @property
    def pays(self) -> bool:
        """Whether an intrinsic reward reaches the advantages (a bonus that pays, paid)."""
        return self.entry_point is not None and self.pays_reward

    # --- settings ---------------------------------------------------------------------------
    def option_names(self) -> list[str]:
        """The names `bonus_options` may set (the config's fields not taken from the run)."""
        cls = self.config_class
        if cls is None:
            return []
        if getattr(cls, "RUN_FIELD", None):  # the run's own settings, options of `illm train`
            return []
        return [f.name for f in dataclasses.fields(cls)]

    def parse_options(self, pairs: Iterable[str]) -> dict[str, Any]:
        """`KEY=VALUE` strings (as `--bonus-option` gives them) -> typed bonus options."""
        from illm_tools.settings import parse_pairs

        return self.typed_options(parse_pairs(pairs, "--bonus-option"))

    def typed_options(self, options: Mapping[str, Any]) -> dict[str, Any]:
        """Bonus options by name, typed as the config's fields; unknown names are refused."""
        allowed = self.option_names()
        unknown = sorted(set(options) - set(allowed))
        if unknown:
            takes = f"it takes {', '.join(allowed)}" if allowed else "it takes none"
            raise UsageError(f"--method {self.name} has no bonus option {', '.join(unknown)}; {takes}")
        hints = typing.get_type_hints(self.config_class) if options else {}
        return {k: _typed(k, hints.get(k), v) for k, v in options.items()}

    def make_config(self, run: Mapping[str, Any], options: Mapping[str, Any]) -> Any:
        """The bonus's config: the run's own (`run[RUN_FIELD]`, a TrainConfig's field: the object,
        or its dict form), else one from `options` and the defaults. Refuses unknown or ill-typed
        options."""
        options = self.typed_options(options)
        cls = self.config_class
        if cls is None:
            return None
        field = getattr(cls, "RUN_FIELD", None)
        if field:
            own = run.get(field)
            return own if isinstance(own, cls) else cls(**(own or {}))
        return cls(**options)

    def build(self, run: Mapping[str, Any], options: Mapping[str, Any], ctx: BonusContext) -> IntrinsicBonus:
        """A new bonus for a run: its config from the run's settings, its sizes from `ctx`."""
        bonus = self.bonus_class.from_config(self.make_config(run, options), ctx)
        if not self.pays_reward:
            bonus.pays_reward = False
        return bonus


def _typed(name: str, hint: Any, value: Any) -> Any:
    """`value` as the field's type (bool, int, float or str); strings come from the command line."""
    if hint in (bool, int, float, str) and isinstance(value, hint) and not (hint is int and isinstance(value, bool)):
        return value
    text = str(value).strip().lower()
    try:
        if hint is bool:
            if text in ("1", "true", "yes", "on"):
                return True
            if text in ("0", "false", "no", "off"):
                return False
            raise ValueError(value)
        if hint is int:
            if isinstance(value, float) and not value.is_integer():
                raise ValueError(value)
            return int(value) if not isinstance(value, str) else int(text)
        if hint is float:
            if isinstance(value, bool):
                raise ValueError(value)
            return float(value)
        if hint is str:
            return str(value)
    except ValueError:
        raise UsageError(f"option {name} must be {hint.__name__}, got {value!r}") from None
    return value  # other types: the config's own validation decides


class MethodRegistry(Registry):
    """The methods' `Registry`, refusing the name an installed plug-in shares with a registered method
    (see the module docstring): `plugins` keeps each entry point read (name -> "module:attribute"),
    `clashes` each one that had a registered method's name (which keeps its entry, so `--help` and
    the other names still work); `get_method` refuses a clashing name in one line naming both."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.plugins: dict[str, str] = {}
        self.clashes: dict[str, str] = {}

    def clash(self, name: str) -> str | None:
        """The one line refusing `name` where an installed plug-in shares it with a registered method."""
        if name not in self.clashes or name not in self._entries:
            return None
        entry = self._entries[name]
        own = entry.summary if isinstance(entry, Method) else str(entry)
        return (f"the installed plug-in method {name!r} ({self.clashes[name]}, entry point group {self.group}) has "
                f"the name of the built-in method {name!r} ({own}): give the plug-in's entry point another name")

    def register(self, name: str, entry: Any, *, replace: bool = False) -> Any:
        if name in self.plugins and not replace:  # a plug-in read first, a built-in registered after it
            self.clashes[name] = self.plugins.pop(name)
            replace = True
        return super().register(name, entry, replace=replace)

    def read_plugins(self, *, again: bool = False) -> list[str]:
        """`Registry.read_plugins`, keeping an entry point whose name is registered (by other than
        that same entry point) out, in `clashes` (found afresh on every reading)."""
        if self._plugins_read and not again:
            return []
        self._plugins_read = True
        self.clashes = {}
        from importlib.metadata import entry_points

        added = []
        for point in entry_points(group=self.group):
            if point.name not in self._entries:
                self._entries[point.name] = self.plugins[point.name] = point.value
                added.append(point.name)
            elif self.plugins.get(point.name) != point.value:
                self.clashes[point.name] = point.value
        return added

    def __delitem__(self, name: str) -> None:
        super().__delitem__(name)
        self.plugins.pop(name, None)
        self.clashes.pop(name, None)


METHODS: Registry[Method] = MethodRegistry("method", "illm.methods", check=Method, hint="--method")
"""Every method by name, in registration order (a live view: methods registered later count, and
installed packages' `illm.methods` entry points, each a `Method`)."""


def register(method: Method, *, replace: bool = False) -> Method:
    """Add a method to `METHODS`; a taken name is refused unless `replace`."""
    return METHODS.register(method.name, method, replace=replace)


def get_method(name: str) -> Method:
    """The method called `name`; one line listing the known ones otherwise, or naming the installed
    plug-in that shares the name with a built-in (`MethodRegistry.clash`)."""
    if not isinstance(name, str):
        raise UsageError(METHODS.unknown(name))
    METHODS.read_plugins()  # once a process: a plug-in may share a registered name
    method = METHODS.load(name)
    clash = METHODS.clash(name)
    if clash:
        raise UsageError(clash)
    return method


def method_help() -> str:
    """`--method`'s help: every method with its summary."""
    return " | ".join(f"{m.name} ({m.summary})" for m in METHODS.values())


# The iLLM methods' default weights: `small` (the paper's / 10), the one setting chosen on the suite's tune half
# (docs/experiments/suite.md); `--bonus-preset paper` gives Appendix B's.
register(Method("illm", "iLLM heads + bonus", "illm_tools.intrinsic.illm:ILLMBonus", preset="small"))
register(Method("illm-noreward", "iLLM heads only, no bonus: paper Table 3", "illm_tools.intrinsic.illm:ILLMBonus",
                pays_reward=False, preset="small"))
register(Method("ppo", "no bonus", None, pays_reward=False))
register(Method("rnd", "Random Network Distillation; advantage weights 2 / 1", "illm_tools.intrinsic.rnd:RNDBonus",
                preset="rnd"))
register(Method("ellm", "ELLM: reward for reaching a goal the LLM suggested (cache task goal)",
                "illm_tools.intrinsic.ellm:ELLMBonus"))
register(Method("ngu", "Never Give Up: episodic kNN novelty x RND life-long factor; intrinsic weight 0.3",
                "illm_tools.intrinsic.ngu:NGUBonus", preset="ngu"))
register(Method("apt", "Active Pre-Training: kNN particle entropy in the rollout", "illm_tools.intrinsic.apt:APTBonus"))
register(Method("illm-shuffled", "iLLM on another cached state's targets (fixed permutation): control",
                "illm_tools.intrinsic.illm:ILLMBonus", target_shuffle=0, preset="small"))
