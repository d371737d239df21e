"""Which oracle answers a state: `ORACLES`, one entry per suite (a name -> its `Oracle` class, as
"module:Class", imported on first use; installed packages add theirs through `illm.oracles` entry
points), looked up by the game the state's prompt names (`family_of(env_id)`).

The oracle backend (`illm_tools.llm.oracle`, `--backend oracle`) asks here which oracle reads a
game (`oracle_for`), which games have one (`known_families`, for its one-line refusal) and every
oracle's version (`versions`, in its fingerprint). A new oracle is one file in this package plus
one line below (or an entry point in a package of its own).
"""

from __future__ import annotations

from illm_tools.errors import UsageError
from illm_tools.oracles.base import Oracle
from illm_tools.registry import Registry


def _oracle_problem(cls) -> str | None:
    """What keeps a class from being an oracle."""
    if not (isinstance(cls, type) and issubclass(cls, Oracle)):
        return "is not an Oracle subclass (illm_tools.oracles.base)"
    if not cls.families or not cls.version:
        return "names no families or no version"
    return None


ORACLES: Registry = Registry("oracle", "illm.oracles", check=_oracle_problem)
"""Suite name -> its oracle's class; the families each one reads decide which answers a state."""
ORACLES.register("babyai", "illm_tools.oracles.babyai:BabyAIOracle")
ORACLES.register("crafter", "illm_tools.oracles.crafter:CrafterOracle")
ORACLES.register("minihack", "illm_tools.oracles.minihack:MiniHackOracle")


def _by_family() -> dict[str, str]:
    """Each game an oracle reads -> that oracle's name; two oracles claiming one game are refused."""
    out: dict[str, str] = {}
    for name in ORACLES:
        for family in ORACLES.load(name).families:
            if family in out:
                raise UsageError(f"the oracles {out[family]!r} and {name!r} both read {family}: unregister one")
            out[family] = name
    return out


def known_families() -> tuple[str, ...]:
    """The games some oracle reads, in registration order."""
    return tuple(_by_family())


def named(families: tuple[str, ...]) -> str:
    """("BabyAI", "MiniGrid", "Crafter") -> "BabyAI, MiniGrid and Crafter"."""
    return " and ".join(filter(None, (", ".join(families[:-1]), families[-1]))) if families else "no game"


def oracle_for(family: str, what: str | None = None) -> str:
    """The name of the oracle that reads the game `family`; a game none reads is refused in one line
    that names those some oracle reads (and `what` was asked about: an env id, else the game)."""
    found = _by_family().get(family)
    if found is None:
        raise UsageError(f"the oracle backend knows {named(known_families())} only, not {what or family}: use an LLM "
                         "backend (--backend transformers) for other suites")
    return found


def versions() -> tuple[str, ...]:
    """Every registered oracle's version, in registration order (the oracle backend's fingerprint)."""
    return tuple(ORACLES.load(name).version for name in ORACLES)
