"""Oracles: annotators that know a game, one per suite, behind the LLM backend contract through the
oracle backend (`illm_tools.llm.oracle`, `--backend oracle`). `base.py` the contract and the prompt's
frame, `registry.py` which oracle answers a state (by the game its prompt names), `babyai.py` the
BabyAI and MiniGrid oracle (its planner in `babyai_planner.py`, `babyai_reading.py`, `babyai_map.py`),
`crafter.py` Crafter's (`crafter_reading.py`, `crafter_paths.py`, `crafter_planner.py`), `minihack.py`
MiniHack's (`minihack_reading.py`). Nothing here imports an environment, a model or numpy: an oracle
reads the prompt's text only (the MiniHack oracle takes NetHack's monster names from nle's tables, game
knowledge, not the env's state)."""
