"""The transformers backend: a loaded causal LM (`illm_tools.llm.loading.LoadedModel`) behind the
`Backend` protocol. Scoring, generation and their shared-prefix form run through the engine's one
driver (`driver.py`); what is here is the iLLM(hop) side, prompts with input embeddings spliced in
(run by the same driver), and the thin delegation."""
from __future__ import annotations

import os
from collections.abc import Sequence

from illm_tools.llm.spliced import SplicedPrompt
from illm_tools.llm.loading import LoadedModel
from illm_tools.llm.registry import DEFAULT_MODEL


class TransformersBackend:
    name = "transformers"
    default_model = DEFAULT_MODEL
    quantises = True
    """`--quant auto` takes the alias's 4-bit on CUDA (`backend.backend_quant`)."""
    local_models = True
    """Its models are files on this machine (`illm models`), which a dry run checks before a grid."""

    def __init__(self, lm: LoadedModel):
        self.lm = lm
        self.model = lm.name
        self.fingerprint = lm.fingerprint
        self.hidden_size = int(lm.hidden_size)

    @property
    def device(self) -> str:
        return str(self.lm.device)

    # --- building ------------------------------------------------------------------------------
    @classmethod
    def load(cls, model: str, *, dtype: str = "bfloat16", quant: str = "none", device: str = "cpu",
             cache_dir: str | os.PathLike | None = None, batch_tokens: int | None = None) -> TransformersBackend:
        from illm_tools.llm.loading import load_model

        return cls(load_model(model, dtype=dtype, quant=quant, device=device, cache_dir=cache_dir,
                              batch_tokens=batch_tokens))

    @staticmethod
    def preload(model: str, *, cache_dir: str | os.PathLike | None = None) -> None:
        from illm_tools.llm.loading import preload

        preload(model, cache_dir=cache_dir)

    @staticmethod
    def model_fingerprint(model: str, *, dtype: str = "bfloat16", quant: str = "none") -> dict:
        from illm_tools.llm import loading

        return loading.model_fingerprint(model, dtype=dtype, quant=quant)

    @staticmethod
    def model_hidden_size(model: str) -> int:
        from illm_tools.llm import loading

        return loading.model_hidden_size(model)

    # --- text ----------------------------------------------------------------------------------
    def score(self, contexts, candidates, *, batch_size: int = 8):
        from illm_tools.llm.driver import score_candidates

        return score_candidates(self.lm, contexts, candidates, batch_size=batch_size)

    def generate(self, prompts, *, max_new_tokens: int = 64, batch_size: int = 8):
        from illm_tools.llm.driver import generate

        return generate(self.lm, prompts, max_new_tokens=max_new_tokens, batch_size=batch_size)

    def score_and_generate(self, contexts, candidates, prompts, *, max_new_tokens: int = 64, batch_size: int = 8):
        """One pass over each state's shared prompt prefix where the model allows it (not on
        sliding-window models), else the two separate paths."""
        from illm_tools.llm.driver import score_and_generate

        if self.shares_prefix:
            return score_and_generate(self.lm, contexts, candidates, prompts, max_new_tokens=max_new_tokens,
                                      batch_size=batch_size)
        return (self.score(contexts, candidates, batch_size=batch_size),
                self.generate(prompts, max_new_tokens=max_new_tokens, batch_size=batch_size))

    @property
    def context_length(self) -> int | None:
        """The model's context in tokens (None: its config states none)."""
        return self.lm.context_length

    def tokens_needed(self, prompt: str, candidates: Sequence[str] | None, max_new_tokens: int, *,
                      window: int = 0, tail: str = "") -> int:
        """The positions one task of a state takes: its prompt, then its longest candidate or its
        generated tokens; a hop prompt (`spliced`) is `prompt` its head, `window` input embeddings,
        then `tail`. Texts whose UTF-8 bytes could not reach the context are not tokenised (a token
        holds at least one byte)."""
        longest = max((len(c.encode()) for c in candidates or ()), default=0)
        bound = len(self.lm.bos_ids) + len(prompt.encode()) + window + len(tail.encode()) + longest + max_new_tokens
        if self.context_length is None or bound <= self.context_length:
            return bound

        def tokens(text: str) -> int:
            return len(self.lm.tokenizer(text, add_special_tokens=False)["input_ids"]) if text else 0

        own = max((tokens(c) for c in candidates or ()), default=0)
        return len(self.lm.encode(prompt)) + window + tokens(tail) + own + max_new_tokens

    @property
    def shares_prefix(self) -> bool:
        """The backend contract's name for a model without a sliding window (`LoadedModel.sliding_window`)."""
        return not self.lm.sliding_window

    def embed(self, texts, *, batch_size: int = 8):
        from illm_tools.llm.generation import embed_texts

        return embed_texts(self.lm, texts, batch_size=batch_size)

    # --- input embeddings (iLLM(hop)) ------------------------------------------------------------
    def input_embeddings(self):
        return self.lm.model.get_input_embeddings().weight

    def last_hidden(self, windows: Sequence):
        """float32 [B, H]: the last hidden state after reading each window [L_i, d] as input
        embeddings (no prompt); windows of one length run as one batch, through the decoder alone
        (the output layer's logits are not needed)."""
        import torch

        out = torch.zeros(len(windows), self.hidden_size)
        by_length: dict[int, list[int]] = {}
        for i, w in enumerate(windows):
            by_length.setdefault(int(w.shape[0]), []).append(i)
        dtype = self.input_embeddings().dtype
        backbone = self.lm.model.base_model
        with torch.inference_mode():
            for rows in by_length.values():
                embeds = torch.stack([windows[i] for i in rows]).to(dtype=dtype, device=self.lm.device)
                out[rows] = backbone(inputs_embeds=embeds, use_cache=False).last_hidden_state[:, -1].float().cpu()
        return out

    def spliced(self, prompts: Sequence[SplicedPrompt], *, max_new_tokens: int = 64, batch_size: int = 8) -> list:
        """Per prompt: `CandidateScores` (candidates given) or `Generation` (none). Each prompt runs
        as one head of input embeddings (head tokens, the window, tail tokens) through the engine's
        driver (prompts of one length batch together, unpadded); candidates are scored after it with
        joint tokenisation of tail and candidate, summaries decoded greedily from it."""
        import torch

        from illm_tools.llm.driver import Work, drive
        from illm_tools.llm.scoring import StatePlan, plan_state

        lm = self.lm
        embed = lm.model.get_input_embeddings()
        bos = len(lm.bos_ids)
        works = []
        for prompt in prompts:
            branches = {}
            if prompt.candidates is not None:
                plan = plan_state(lm, prompt.tail, list(prompt.candidates))
                tail_ids = plan.prefix[bos:]
                branches["action"] = StatePlan([], plan.continuations, plan.skip)
            else:
                tail_ids = lm.tokenizer(prompt.tail, add_special_tokens=False)["input_ids"]
            with torch.inference_mode():
                parts = [embed(torch.as_tensor(ids, dtype=torch.long, device=lm.device)).float().cpu()
                         for ids in (lm.encode(prompt.head), tail_ids) if ids]
            works.append(Work(embeds=torch.cat([parts[0], prompt.window.float(), *parts[1:]]), branches=branches,
                              suffix=None if prompt.candidates is not None else ()))
        answers = drive(lm, works, batch_size=batch_size, max_new_tokens=max_new_tokens)
        return [a.scores["action"] if p.candidates is not None else a.generation for p, a in zip(prompts, answers)]
