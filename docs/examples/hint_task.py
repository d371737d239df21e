"""A language task as an illm plug-in: `illm annotate DATA --tasks action,summary,hint`.

One entry and one template file (templates/hint.txt beside this one): a `text` task, whose answer
is generated (at most `max_new_tokens`, greedy) and embedded. Annotation, the cache, iLLM's heads
(one more head, f_hint), its bonus (1 - cosine, weighted by `--task-weight hint=W`) and the live
fallback take it from there. The template's name and version are part of every key: change the
text, bump the version. tests/test_docs_examples.py annotates and trains with it.
"""

from __future__ import annotations

from pathlib import Path

from illm_tools.tasks.registry import LanguageTask

TASK = LanguageTask(
    "hint",
    "text",  # "ranking" scores the valid actions instead
    {"shared": ("hint", 1), "paper": ("hint", 1)},  # per prompt layout: (template file's name, its version)
    max_new_tokens=12,
    template_dir=str(Path(__file__).parent / "templates"),
    description="one hint for the player",
)
