"""The goal task's answer: the goal strings of a generated list (ELLM's goals, `parse_goals`)."""

from __future__ import annotations

import re

GOAL_PARSER_VERSION = 1
"""Version of `parse_goals`: part of the goal task's decoding parameters, so of every goal key
(the parsed list is stored in the row). Bump it when the parsing changes."""
MAX_GOALS = 8
"""Goals kept per state (the first ones the model wrote)."""
MAX_GOAL_WORDS = 8
"""Longer items are not "a single valid word or a phrase" (the prompt's words) and are dropped."""


_PROMPT_LINE = re.compile(r"(you are an expert player|recent player's history|valid actions|suggest the next goal"
                          r"|observation \d+\s*:|action \d+\s*:)", re.IGNORECASE)
_INLINE_NUMBER = re.compile(r"\s(?=\d{1,2}[.)]\s)")
_MARKER = re.compile(r"^(?:[-*\u2022]+|\(?\d{1,2}[.):])\s*")
_LABEL = re.compile(r"^(?:next\s+)?goals?(?:\s*\d+)?\s*[:\-]\s*", re.IGNORECASE)
_QUOTES = "\"'`\u201c\u201d\u2018\u2019()[]{}<> "
_COPIES = ("you see ", "you carry ")


def parse_goals(text: str, truncated: bool = False) -> list[str]:
    """The goal strings of a generated answer to the `goal` prompt (version `GOAL_PARSER_VERSION`);
    `truncated`: the generation was cut at the goal task's token limit (not ended by the model).

    1. Lines are read in order; a blank line after the first goal, or a line that starts a prompt
       of its own ("You are an expert player", "Recent player's history", "Observation N:",
       "Action N:", "Valid actions", "Suggest the next goal"), ends the list: small models go on
       writing the prompt again.
    2. Each line is split into items at commas, semicolons and inline numbering ("1. a 2. b").
    3. Each item loses a leading list marker ("-", "*", "\u2022", "1.", "2)"), a label ("Goal:",
       "Goals:", "Goal 1:"), quotes and brackets around it, and trailing ".", "!", "?", ":"; its
       whitespace is collapsed and it is lower-cased.
    4. Dropped: empty items, items without a letter, items longer than `MAX_GOAL_WORDS` words (not
       "a single valid word or a phrase", the prompt's words), and copies of the observation
       ("you see ...", "you carry ...").
    5. In a truncated generation whose list did not end before the cut (by 1.), the last item is
       dropped: it may be cut mid-phrase ("- Open door\n- Open").
    6. Duplicates are dropped (first kept) and at most `MAX_GOALS` goals are returned.
    """
    items: list[str] = []
    ended = False
    for line in text.splitlines():
        if not line.strip():
            if items:
                ended = True
                break
            continue
        if _PROMPT_LINE.match(_MARKER.sub("", line.strip())):
            ended = True
            break
        items += re.split(r"[,;]", _INLINE_NUMBER.sub(";", line))
    if truncated and not ended:
        items = items[:-1]
    goals: list[str] = []
    for item in items:
        goal = _clean_goal(item)
        if goal and goal not in goals:
            goals.append(goal)
    return goals[:MAX_GOALS]


def _clean_goal(item: str) -> str | None:
    """One list item as a goal (steps 3 and 4 of `parse_goals`), None when it is not one."""
    goal = _MARKER.sub("", item.strip())
    goal = _LABEL.sub("", goal)
    goal = " ".join(goal.strip(_QUOTES).rstrip(".!?:").strip(_QUOTES).split()).lower()
    if not goal or not re.search(r"[a-z]", goal) or len(goal.split()) > MAX_GOAL_WORDS:
        return None
    if goal.startswith(_COPIES):
        return None
    return goal
