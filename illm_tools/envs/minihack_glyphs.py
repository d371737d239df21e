"""What each NetHack glyph is called in the MiniHack renderer's text (`illm_tools.envs.minihack_text`):
monsters, objects as a player sees them before identifying them, dungeon features and traps, with
their articles and plurals; the table of every glyph's name, built once. Split from the renderer,
which places the named things on the map and writes the observation; the choices are explained in
its module docstring."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from nle import nethack  # no minihack import here: minihack's import warns (pkg_resources)

# Tiers: the order in which map phrases are chosen when there are more than _MAX_MAP_PHRASES.
_GOAL, _CREATURE_OR_OBJECT, _FEATURE = 0, 1, 2

# cmap indices (NetHack's defsyms) of the features described: doorway, open and closed doors, iron
# bars, tree (12-18); stairs, ladders, altar, grave, throne, sink, fountain, water, ice, lava,
# drawbridges (23-38); the Plane of Water's water, traps, vibrating square (41-64); poison cloud (77).
_DESCRIBED_CMAP = (*range(12, 19), *range(23, 39), *range(41, 65), 77)
_CMAP_RENAMES = {"molten lava": "lava", "opulent throne": "throne"}
_CMAP_ARTICLES = {**dict.fromkeys(("water", "lava", "ice", "iron bars"), ""),
                  **dict.fromkeys(("staircase up", "staircase down", "ladder up", "ladder down"), "the")}
_M2_PNAME, _G_UNIQ = 0x00080000, 0x1000  # NetHack's monflag.h: a proper name; a unique monster
_CLASS_NOUNS = {nethack.POTION_CLASS: "potion", nethack.RING_CLASS: "ring", nethack.WAND_CLASS: "wand",
                nethack.SCROLL_CLASS: "scroll", nethack.SPBOOK_CLASS: "spellbook",
                nethack.AMULET_CLASS: "amulet"}
# Armor whose looks NetHack shuffles each game (o_init.c): named by kind, as the glyph's object
# name would be wrong (see the module docstring).
_SHUFFLED_ARMOR = {
    **dict.fromkeys(("helmet", "helm of brilliance", "helm of opposite alignment", "helm of telepathy"),
                    "helmet"),
    **dict.fromkeys(("cloak of protection", "cloak of invisibility", "cloak of magic resistance",
                     "cloak of displacement"), "cloak"),
    **dict.fromkeys(("leather gloves", "gauntlets of fumbling", "gauntlets of power",
                     "gauntlets of dexterity"), "gloves"),
    **dict.fromkeys(("speed boots", "water walking boots", "jumping boots", "elven boots", "kicking boots",
                     "fumble boots", "levitation boots"), "boots"),
}
_PAIRS = ("boots", "shoes", "gloves", "lenses")
_IRREGULAR_PLURALS = {"man": "men", "woman": "women", "mouse": "mice", "louse": "lice", "wolf": "wolves",
                      "werewolf": "werewolves", "dwarf": "dwarves", "elf": "elves", "thief": "thieves",
                      "knife": "knives", "staff": "staves", "tooth": "teeth", "foot": "feet"}


@dataclass(frozen=True)
class _Thing:
    name: str
    """Singular, without article: "newt", "lava", "staircase down", "pair of boots"."""
    tier: int
    article: str | None = None
    """None: "a" or "an"; "the"; "": none (proper names, and mass nouns, which are never counted)."""


def _a(noun: str) -> str:
    vowel = noun[0].lower() in "aeiou" and not noun.startswith(("one", "eu", "uni", "use", "ura", "uke"))
    return f"{'an' if vowel else 'a'} {noun}"


def _plural(noun: str) -> str:
    head, sep, tail = noun.partition(" of ")  # "pair of boots" -> "pairs of boots"
    if not sep and noun.endswith((" up", " down")):  # "staircase down" -> "staircases down"
        head, tail = noun.rsplit(" ", 1)
        sep = " "
    *words, last = head.split(" ")
    if last in _IRREGULAR_PLURALS:
        last = _IRREGULAR_PLURALS[last]
    elif last.endswith(("s", "x", "z", "ch", "sh")):
        last += "es"
    elif last.endswith("y") and last[-2:-1] not in ("a", "e", "i", "o", "u"):
        last = last[:-1] + "ies"
    else:
        last += "s"
    return " ".join((*words, last)) + sep + tail


def _noun_phrase(thing: _Thing, count: int) -> str:
    if thing.article == "":
        return thing.name
    if count > 1:
        return f"{count} {_plural(thing.name)}"
    return f"{thing.article} {thing.name}" if thing.article else _a(thing.name)


def _monster(index: int) -> _Thing:
    monster = nethack.permonst(index)
    article = "" if monster.mflags2 & _M2_PNAME else "the" if monster.geno & _G_UNIQ else None
    return _Thing(monster.mname, _CREATURE_OR_OBJECT, article)


def _object(index: int) -> _Thing:
    """An object as a player sees it before identifying it (see the module docstring)."""
    objclass = nethack.objclass(index)
    cls = ord(objclass.oc_class)
    name, looks = nethack.OBJ_NAME(objclass), nethack.OBJ_DESCR(objclass)
    if cls == nethack.COIN_CLASS:
        return _Thing("gold", _CREATURE_OR_OBJECT, "")
    if cls in _CLASS_NOUNS:
        noun = _CLASS_NOUNS[cls]
    elif cls == nethack.GEM_CLASS and looks:
        noun = f"{looks} {'stone' if looks == 'gray' else 'gem'}"
    else:
        noun = _SHUFFLED_ARMOR.get(name) if cls == nethack.ARMOR_CLASS else None
        noun = noun or looks or name
    return _Thing(f"pair of {noun}" if noun.endswith(_PAIRS) else noun, _CREATURE_OR_OBJECT)


def _feature(cmap: int) -> _Thing | None:
    if cmap not in _DESCRIBED_CMAP:
        return None
    name = nethack.symdef.from_idx(cmap).explanation
    name = _CMAP_RENAMES.get(name, name)
    tier = _GOAL if name in ("staircase down", "ladder down") else _FEATURE
    return _Thing(name, tier, _CMAP_ARTICLES.get(name))


def _glyph_thing(glyph: int) -> _Thing | None:
    if nethack.glyph_is_pet(glyph):
        return _Thing(f"tame {_monster(nethack.glyph_to_mon(glyph)).name}", _CREATURE_OR_OBJECT)
    if nethack.glyph_is_monster(glyph):  # seen, detected and ridden monsters
        return _monster(nethack.glyph_to_mon(glyph))
    if nethack.glyph_is_invisible(glyph):
        return _Thing("unseen creature", _CREATURE_OR_OBJECT)
    if nethack.glyph_is_body(glyph):
        return _Thing(f"{_monster(glyph - nethack.GLYPH_BODY_OFF).name} corpse", _CREATURE_OR_OBJECT)
    if nethack.glyph_is_statue(glyph):
        monster = _monster(nethack.glyph_to_mon(glyph))
        return _Thing(f"statue of {_noun_phrase(monster, 1)}", _CREATURE_OR_OBJECT)
    if nethack.glyph_is_normal_object(glyph):
        return _object(nethack.glyph_to_obj(glyph))
    if nethack.glyph_is_cmap(glyph):  # dungeon features and traps
        return _feature(nethack.glyph_to_cmap(glyph))
    return None  # explosions, zaps, the engulfer's inside, warnings


@functools.lru_cache(maxsize=1)
def _glyph_table() -> tuple[tuple[_Thing | None, ...], np.ndarray]:
    """What every glyph shows (None: not described), and a boolean mask of the described glyphs."""
    things = tuple(_glyph_thing(glyph) for glyph in range(nethack.MAX_GLYPH))
    described = np.array([thing is not None for thing in things] + [False])  # + NO_GLYPH
    return things, described
