"""A request to `illm serve`, read and checked whole on arrival against the server's own setup
(`ServerTerms`): the JSON (any shape: 400 in one line), each field's type and size (`ServeLimits`),
the setup the request declares (it must be the server's: 409 naming the difference), the env and
the backend's own check of it, and a hop state's window (its frames' shape and dtype are the
env's, decided here, never by the client). What passes is a list of (record, visits) under the
server's `AnnotationSetup`: rows the server writes carry its setup only."""

from __future__ import annotations

import base64
import binascii
import json
import math

import numpy as np

from illm_tools.errors import IllmError
from illm_tools.serve.config import ServeLimits
from illm_tools.tasks.prompt_config import PromptConfig
from illm_tools.tasks.annotation_setup import WIRE_FIELDS, AnnotationSetup
from illm_tools.tasks.state import StateRecord

MAX_ID_CHARS = 256
"""Characters of a client name, a session, an env id, a renderer or a fingerprint."""
REQUEST_FIELDS = ("client", "session", "model_fingerprint", *WIRE_FIELDS, "states", "wait")
"""The top-level fields of a request (any other: 400, so a body carries nothing the server does not read)."""
STATE_FIELDS = ("mission", "history", "observation", "valid_actions", "visits", "frames", "prev_actions")
"""The fields of one state of a request (any other: 400)."""


class RequestError(ValueError):
    """A request the server refuses: its HTTP status and one line (429, 503: with Retry-After seconds)."""

    def __init__(self, status: int, message: str, retry_after: int | None = None):
        super().__init__(message)
        self.status = status
        self.retry_after = retry_after


def _no_constant(name: str):
    raise ValueError(f"{name} is not JSON")


def _finite(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{text[:40]} is not a finite number")
    return value


def read_json(raw: bytes):
    """The body as JSON; RequestError(400) in one line for anything else (bad bytes, NaN or
    Infinity, nesting deeper than the parser's recursion limit)."""
    try:
        return json.loads(raw, parse_constant=_no_constant, parse_float=_finite)
    except (ValueError, RecursionError, UnicodeDecodeError) as e:
        what = "nested too deeply" if isinstance(e, RecursionError) else str(e).splitlines()[0][:200]
        raise RequestError(400, f"the request body is not JSON ({what})") from None


def text(value, name: str, limit: int, status: int = 413) -> str:
    """`value` when it is a string of at most `limit` characters, else RequestError (400 not a string)."""
    if not isinstance(value, str):
        raise RequestError(400, f"{name} must be a string, got {type(value).__name__}")
    if len(value) > limit:
        raise RequestError(status, f"{name} has {len(value):,} characters, more than the server's limit {limit:,}")
    return value


MAX_WAIT = 120.0
"""The longest a request may ask to be held until its states land (`"wait"`)."""


def unknown_fields(item: dict, known: tuple[str, ...], what: str) -> None:
    """RequestError(400) in one line when `item` has a key outside `known`."""
    extra = [k for k in item if k not in known]
    if extra:
        names = ", ".join(repr(str(k)[:40]) for k in extra[:4])
        names += f" and {len(extra) - 4:,} more" if len(extra) > 4 else ""
        raise RequestError(400, f"{what} has fields this server does not read ({names}): send only {', '.join(known)}")


def requested_wait(body: dict) -> float:
    """The seconds a request asks to be held until its states land (`"wait"`, default 0)."""
    wait = body.get("wait", 0)
    if isinstance(wait, bool) or not isinstance(wait, (int, float)) or not 0 <= wait <= MAX_WAIT:
        raise RequestError(400, f"wait must be a number of seconds in 0..{MAX_WAIT:g}, got {str(wait)[:40]}")
    return float(wait)


def trainer_of(body: dict) -> tuple[str, str]:
    """The trainer a request comes from: its (client, session)."""
    return text(body["client"], "client", MAX_ID_CHARS, 400), text(body["session"], "session", MAX_ID_CHARS, 400)


def whole(value, name: str, low: int, high: int) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
        raise RequestError(400, f"{name} must be a whole number in {low}..{high:,}, got {str(value)[:40]}")
    return value


class ServerTerms:
    """The setup a server annotates under (its model's options, history, layout, tasks, hop
    settings) and the request checks that follow from it and from its limits."""

    def __init__(self, llm, *, prompt: PromptConfig, tasks: tuple[str, ...], limits: ServeLimits):
        self.llm, self.prompt, self.tasks, self.limits = llm, prompt, tuple(tasks), limits
        self.history_len, self.layout = prompt.history_len, prompt.layout
        self._envs: dict[tuple[str, bool], tuple[AnnotationSetup, tuple | None]] = {}  # one per known env and mode

    def options(self) -> str:
        """The flags that select what it serves ("--history 0 --layout shared --tasks action,summary")."""
        return f"{self.prompt.options()} --tasks {','.join(self.tasks)}"

    def describe(self) -> dict:
        return {"history_len": self.history_len, "layout": self.layout, "tasks": list(self.tasks),
                "hop_seed": self.prompt.hop_seed, "hop_beta": self.prompt.hop_beta}

    def of_request(self, body: dict) -> AnnotationSetup:
        """The server's setup for the env the request names, once what the request declares has been
        compared with it: a difference is refused (409) in one line naming it."""
        env_id = text(body.get("env_id"), "env_id", MAX_ID_CHARS, 400)
        renderer = text(body.get("renderer"), "renderer", MAX_ID_CHARS, 400)
        history_len = whole(body.get("history_len"), "history_len", 0, 10**6)
        layout = text(body.get("layout"), "layout", MAX_ID_CHARS, 400)
        tasks = body.get("tasks")
        if not isinstance(tasks, list) or not tasks or len(tasks) > 16:
            raise RequestError(400, "tasks must be a list of 1 to 16 task names")
        tasks = [text(t, "a task", 64, 400) for t in tasks]
        hop = renderer.startswith("hop@")
        setup, _ = self.env(env_id, hop)
        differ = []
        if history_len != self.history_len:
            differ.append(f"--history {self.history_len} (the request's {history_len})")
        if layout != self.layout:
            differ.append(f"--layout {self.layout} (the request's {layout[:40]!r})")
        if renderer != setup.renderer:
            differ.append(f"renderer {setup.renderer}{' (--hop-seed, --hop-beta)' if hop else ''} (the request's "
                          f"{renderer[:80]!r})")
        unserved = [t[:40] for t in tasks if t not in self.tasks]
        if unserved:
            differ.append(f"--tasks {','.join(self.tasks)} (the request reads {','.join(unserved)} too)")
        if differ:
            raise RequestError(409, f"this server annotates with {'; '.join(differ)}: its rows would be another setup "
                                    "in the shared cache; train with the server's options or start a server for yours")
        return setup

    def env(self, env_id: str, hop: bool) -> tuple[AnnotationSetup, tuple | None]:
        """(the server's setup, a hop frame's (shape, dtype) or None) of an env in a mode: the env
        must be one illm knows and the backend can read (its own check), in that mode."""
        found = self._envs.get((env_id, hop))
        if found is not None:
            return found
        from illm_tools.envs import suite_of
        from illm_tools.tasks.registry import get_task

        try:
            suite = suite_of(env_id)
            frame = None
            if hop:
                unfit = [t for t in self.tasks if not get_task(t).hop]
                if unfit:
                    raise RequestError(400, f"this server's --tasks {','.join(unfit)} have no hop form: it annotates no "
                                            "hop states")
                spec = suite.obs_spec(env_id)
                blank = np.asarray(suite.hop_input(np.zeros(spec.shape, dtype=np.dtype(spec.dtype))))
                frame = (tuple(int(d) for d in blank.shape), blank.dtype)
            setup = self.prompt.of(env_id, self.tasks, hop=hop)
            self.llm.check_use(env_id, setup.renderer)  # the backend refuses what it cannot read (hop, a suite)
        except IllmError as e:
            raise RequestError(400, str(e).splitlines()[0]) from None
        self._envs[(env_id, hop)] = found = (setup, frame)  # bounded: the envs illm knows, two modes each
        return found

    def parse_state(self, item, setup: AnnotationSetup) -> tuple[StateRecord, int]:
        """(record, visits) of one entry of `states`, every field checked against the limits; a hop
        state with its window decoded and checked (`_hop_record`)."""
        limits = self.limits
        if not isinstance(item, dict):
            raise RequestError(400, "each state must be an object with mission, history, observation, valid_actions")
        missing = [k for k in ("mission", "history", "observation", "valid_actions") if k not in item]
        if missing:
            raise RequestError(400, f"a state lacks {', '.join(missing)}")
        unknown_fields(item, STATE_FIELDS, "a state")
        history = item["history"]
        if not isinstance(history, list) or not all(isinstance(p, list) and len(p) == 2 for p in history):
            raise RequestError(400, "history must be a list of [observation, action] pairs")
        if len(history) > self.history_len:
            raise RequestError(400, f"a state has {len(history)} history steps, more than the server's --history "
                                    f"{self.history_len}")
        actions = item["valid_actions"]
        if not isinstance(actions, list) or not actions:
            raise RequestError(400, "valid_actions must be a non-empty list of strings")
        if len(actions) > limits.max_actions:
            raise RequestError(413, f"a state has {len(actions):,} valid actions, more than the server's --max-actions "
                                    f"{limits.max_actions}")
        actions = tuple(text(a, "a valid action", limits.max_action_chars) for a in actions)
        visits = whole(item.get("visits", 1), "visits", 0, limits.max_visits)
        chars = limits.max_text_chars
        record = StateRecord(text(item["mission"], "mission", chars),
                             tuple((text(o, "a history observation", chars), text(a, "a history action",
                                                                                    limits.max_action_chars))
                                   for o, a in history),
                             text(item["observation"], "observation", chars), actions)
        if setup.hop:
            return self._hop_record(record, item, self.env(setup.env_id, True)[1]), visits
        if "frames" in item or "prev_actions" in item:
            raise RequestError(400, "a text state carries no frames (the request's renderer is not a hop renderer)")
        return record, visits

    def _hop_record(self, record: StateRecord, item: dict, frame: tuple) -> StateRecord:
        """The hop state of a request entry: its window decoded (each frame of the env's shape and
        dtype, its bytes exactly that size), and checked against the content names its keys are made
        of, so a window that does not match its names never reaches the cache or the engine."""
        from illm_tools.hop.context import HopRecord, step_name

        shape, dtype = frame
        size = math.prod(shape) * dtype.itemsize
        encoded = 4 * math.ceil(size / 3)
        frames, prev = item.get("frames"), item.get("prev_actions")
        n = len(record.history) + 1
        if not isinstance(frames, list) or not isinstance(prev, list) or len(frames) != n or len(prev) != n:
            raise RequestError(400, f"a hop state needs frames and prev_actions for its {n} window steps")
        raws = []
        for f in frames:
            if not isinstance(f, dict) or not isinstance(f.get("data"), str) or not isinstance(f.get("shape"), list):
                raise RequestError(400, "a hop frame is {shape, dtype, base64 data}")
            try:
                same = [int(d) for d in f["shape"]] == list(shape) and np.dtype(f.get("dtype")) == dtype
            except (TypeError, ValueError):
                same = False
            if not same or len(f["data"]) != encoded:
                raise RequestError(400, f"a hop frame of this env is {list(shape)} {dtype} ({size:,} bytes, as the "
                                        "server's env says): the request's is another")
            try:
                raws.append(np.frombuffer(base64.b64decode(f["data"], validate=True), dtype=dtype).reshape(shape))
            except (ValueError, binascii.Error) as e:
                raise RequestError(400, f"a hop frame's data is not base64 of its shape ({e})") from None
        actions = record.valid_actions
        if not all(isinstance(a, int) and not isinstance(a, bool) and -1 <= a < len(actions) for a in prev):
            raise RequestError(400, f"prev_actions must be action indices in -1..{len(actions) - 1}")
        names = [name for name, _ in record.history] + [record.observation]
        for j, (raw, a, name) in enumerate(zip(raws, prev, names)):
            if step_name(raw, actions[a] if a >= 0 else None) != name:
                raise RequestError(400, f"hop window step {j} does not match its content name: the frames or "
                                        "previous actions are not the state's")
            if j and record.history[j - 1][1] != actions[a]:
                raise RequestError(400, f"hop window step {j}: its previous action is not the history's action")
        return HopRecord(record.mission, record.history, record.observation, record.valid_actions,
                         frames=tuple(raws), prev_actions=tuple(prev))
