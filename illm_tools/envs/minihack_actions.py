"""Readable names for NLE's actions, as MiniHack-Text's prompts list them ("move north", "run
northeast", "pick up", "put on", "drink (quaff)", "fire"): a name per enum member, told apart by
enum class as well as value. Split from the renderer (`illm_tools.envs.minihack_text`), which writes
the observation; the names are part of its version (CHANGING ONE MUST BUMP `RENDERER_VERSION`)."""
from __future__ import annotations

import enum
from collections.abc import Sequence

_COMPASS = {"N": "north", "NE": "northeast", "E": "east", "SE": "southeast", "S": "south",
            "SW": "southwest", "W": "west", "NW": "northwest"}
_TYPED = {"PLUS": "plus sign", "MINUS": "minus sign", "SPACE": "space", "APOS": "apostrophe",
          "QUOTE": "quotation mark", "DOLLAR": "dollar sign"}
# (enum class, member) -> name; members missing here are named after themselves ("apply", "kick").
_ACTION_NAMES = {
    ("MiscDirection", "UP"): "go up the stairs",
    ("MiscDirection", "DOWN"): "go down the stairs",
    ("MiscDirection", "WAIT"): "wait",
    ("MiscAction", "MORE"): "next message",
    ("Command", "EXTCMD"): "extended command",
    ("Command", "EXTLIST"): "list extended commands",
    ("Command", "ADJUST"): "adjust inventory letters",
    ("Command", "ANNOTATE"): "annotate level",
    ("Command", "ATTRIBUTES"): "show attributes",
    ("Command", "AUTOPICKUP"): "toggle autopickup",
    ("Command", "CALL"): "call (name)",
    ("Command", "CAST"): "cast a spell",
    ("Command", "CLOSE"): "close a door",
    ("Command", "CONDUCT"): "show conduct",
    ("Command", "DROPTYPE"): "drop several",
    ("Command", "ENHANCE"): "enhance skills",
    ("Command", "ESC"): "escape",
    ("Command", "FORCE"): "force a lock",
    ("Command", "GLANCE"): "glance at a symbol",
    ("Command", "HISTORY"): "show history",
    ("Command", "INVENTORY"): "show inventory",
    ("Command", "INVENTTYPE"): "show inventory of one kind",
    ("Command", "KNOWN"): "show discoveries",
    ("Command", "KNOWNCLASS"): "show discoveries of one class",
    ("Command", "LOOK"): "look here",
    ("Command", "MONSTER"): "use monster ability",
    ("Command", "MOVE"): "move without picking up",
    ("Command", "MOVEFAR"): "run without picking up",
    ("Command", "OFFER"): "offer a sacrifice",
    ("Command", "OPEN"): "open a door",
    ("Command", "OVERVIEW"): "dungeon overview",
    ("Command", "PICKUP"): "pick up",
    ("Command", "PUTON"): "put on",
    ("Command", "QUAFF"): "drink (quaff)",
    ("Command", "QUIVER"): "fill quiver",
    ("Command", "REDRAW"): "redraw screen",
    ("Command", "REMOVE"): "remove an accessory",
    ("Command", "RUSH2"): "rush (alternative)",
    ("Command", "SEEALL"): "show equipment in use",
    ("Command", "SEEAMULET"): "show amulet",
    ("Command", "SEEARMOR"): "show armor",
    ("Command", "SEEGOLD"): "count gold",
    ("Command", "SEERINGS"): "show rings",
    ("Command", "SEESPELLS"): "show spells",
    ("Command", "SEETOOLS"): "show tools in use",
    ("Command", "SEETRAP"): "show adjacent trap",
    ("Command", "SEEWEAPON"): "show weapon",
    ("Command", "SWAP"): "swap weapons",
    ("Command", "TAKEOFF"): "take off",
    ("Command", "TAKEOFFALL"): "take off all armor",
    ("Command", "TIP"): "tip a container",
    ("Command", "TURN"): "turn undead",
    ("Command", "TWOWEAPON"): "toggle two-weapon combat",
    ("Command", "VERSION"): "show version",
    ("Command", "VERSIONSHORT"): "show short version",
    ("Command", "WHATDOES"): "what does a key do",
    ("Command", "WHATIS"): "what is a symbol",
    ("Command", "WIPE"): "wipe face",
}


def _action_name(action: enum.Enum) -> str:
    kind, name = type(action).__name__, action.name
    if kind == "CompassDirection":
        return f"move {_COMPASS[name]}"
    if kind == "CompassDirectionLonger":  # Shift + direction: run until something interesting
        return f"run {_COMPASS[name]}"
    if kind == "TextCharacters":
        return f"type {_TYPED.get(name, name.removeprefix('NUM_'))}"
    return _ACTION_NAMES.get((kind, name), name.lower().replace("_", " "))


def action_names(actions: Sequence[enum.Enum]) -> tuple[str, ...]:
    """Readable lower-case names of an env's actions (`env.unwrapped.actions`, NLE enum members),
    in order: "move north", "run northeast", "pick up", "put on", "drink (quaff)", "apply", ...
    Distinct members get distinct names: members are told apart by enum class as well as value
    (TextCharacters.PLUS is "type plus sign", Command.SEESPELLS, the same key, "show spells")."""
    return tuple(_action_name(action) for action in actions)
