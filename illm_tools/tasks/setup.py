"""What, besides the state and the model, decides an annotation's keys, as one value: the env and
its text renderer (or the hop translation's settings), the language tasks, the history length and
the template layout (each task's template version follows from the layout). `illm annotate`, a
training run's targets and live fallback, and `illm serve` build their prompt builders from one
(`AnnotationSetup.builder`), and a trainer sends it to a server as its `wire()` form, which the
server reads back with `from_wire` (one line naming what is wrong).

The hop renderer's name lives here too: the renderer field of hop keys is the translation's
settings (`hop_renderer`), read back by `parse_hop_renderer`.
"""

from __future__ import annotations

from dataclasses import dataclass

from illm_tools.errors import UsageError
from illm_tools.tasks.prompts import DEFAULT_TASKS, LAYOUTS, PromptBuilder
from illm_tools.tasks.registry import parse_tasks

HOP_VERSION = 2
"""Version of the hop record format and translation; part of every hop cache key (bump on change).
2: Crafter's pictures are grey-scaled before the translation (`Suite.hop_frame`)."""


def hop_renderer(seed: int, beta: float, window: int) -> str:
    """The `renderer` field of hop keys: the translation's settings (the model is in the key already)."""
    return f"hop@{HOP_VERSION}:seed={int(seed)}:beta={float(beta)!r}:window={int(window)}"


def parse_hop_renderer(renderer: str) -> dict | None:
    """{"seed", "beta", "window"} of a hop renderer string, None for a text renderer."""
    if not renderer.startswith("hop@"):
        return None
    fields = dict(part.split("=", 1) for part in renderer.split(":")[1:])
    return {"seed": int(fields["seed"]), "beta": float(fields["beta"]), "window": int(fields["window"])}


WIRE_FIELDS = ("env_id", "renderer", "history_len", "layout", "tasks")
"""The setup's fields in a live-annotation request (`illm serve`)."""


@dataclass(frozen=True)
class AnnotationSetup:
    """The key inputs an annotation shares besides the state and the model (module docstring)."""

    env_id: str
    """The env whose states are annotated (its game line opens every prompt)."""
    renderer: str
    """The env's text renderer (name@version), or a hop renderer (`hop_renderer`)."""
    tasks: tuple[str, ...] = DEFAULT_TASKS
    """The language tasks (`illm_tools.tasks.registry`)."""
    history_len: int = 3
    """Observation/action pairs of history in the prompts."""
    layout: str = "shared"
    """Template layout: shared or paper."""

    def __post_init__(self) -> None:
        for name in ("env_id", "renderer"):
            if not isinstance(getattr(self, name), str):
                raise UsageError(f"{name} must be a string, got {type(getattr(self, name)).__name__}")
        object.__setattr__(self, "tasks", parse_tasks(self.tasks, "tasks"))
        if self.layout not in LAYOUTS:
            raise UsageError(f"layout must be one of {', '.join(LAYOUTS)}, got {self.layout!r}")
        if not isinstance(self.history_len, int) or isinstance(self.history_len, bool) or self.history_len < 0:
            raise UsageError(f"history_len must be a whole number >= 0, got {self.history_len!r}")
        if self.hop:
            try:
                parse_hop_renderer(self.renderer)
            except (KeyError, ValueError):
                raise UsageError(f"renderer {self.renderer!r} is not a hop renderer "
                                 "(hop@N:seed=..:beta=..:window=..)") from None

    @property
    def hop(self) -> bool:
        """Whether the states are hop windows (iLLM(hop)) rather than text."""
        return self.renderer.startswith("hop@")

    def builder(self, model: str, model_fingerprint: str) -> PromptBuilder:
        """The prompt builder of this setup for a model (its spec and fingerprint hash)."""
        return PromptBuilder(env_id=self.env_id, renderer=self.renderer, model=model,
                             model_fingerprint=model_fingerprint, history_len=self.history_len, layout=self.layout)

    def wire(self) -> dict:
        """The JSON fields of a live-annotation request (`WIRE_FIELDS`)."""
        return {"env_id": self.env_id, "renderer": self.renderer, "history_len": self.history_len,
                "layout": self.layout, "tasks": list(self.tasks)}

    @classmethod
    def from_wire(cls, body: dict) -> AnnotationSetup:
        """The setup of a request body (`wire()`'s fields); UsageError in one line when one is
        missing or wrong."""
        missing = [k for k in WIRE_FIELDS if k not in body]
        if missing:
            raise UsageError(f"the request lacks {', '.join(missing)}")
        return cls(**{k: body[k] for k in WIRE_FIELDS})
