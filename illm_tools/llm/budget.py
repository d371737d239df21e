"""What one engine batch may hold, in tokens, and the batches that respect it.

A state's cost to the engine is its tokens, not its count: its prompt (the prefix every candidate
and the summary continue), its candidates packed behind it (`illm_tools.llm.packed`) and the
summary's decoded tokens. Batches are formed by a token budget, as vLLM and SGLang bound theirs
(`max_num_batched_tokens`): states sorted by their tokens, then taken while the batch's padded
size (states x the widest state's tokens) stays within the budget and its count within
`--batch-size`. A state alone over the budget is a batch of its own (the context length, checked
before the engine, bounds it).

The packed candidates' attention mask (`illm_tools.llm.packed`) is the one part that grows with the
square of a state's tokens: [rows, fed, prefix + fed] entries for a batch whose widest row feeds
`fed` tokens (lead and candidates) behind a `prefix` of cached columns. Its bytes (`mask_bytes`),
in tokens of `token_bytes`, count in a batch's padded size beside its tokens; a state whose mask
alone is over the budget has its candidates scored in groups behind the one cached prefix, each
group's mask within the budget (`packed.packed_logprobs`; a single candidate is never split).

The default budget comes from the memory the machine has when the model loads: free RAM on a
CPU (MemAvailable), free device memory on CUDA, of which `SHARE` is given to the batches, divided
by what a token holds at the peak (`token_bytes`: its keys and values in every layer, held up to
`KV_COPIES` times along the way from prefill to decoding, and its share of one layer's
activations). `--batch-tokens` sets it instead.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

SHARE = 0.25
"""The share of the free memory at load that the batches may take (the rest: the trainer, the
environments, other processes, the allocator's slack)."""
KV_COPIES = 3
"""Copies of a token's keys and values alive at once at worst: the shared prompt prefix, a task's
own continuation of it (the summary's prompt), and the decoding buffer it is copied into."""
MIN_TOKENS = 512
"""The smallest default budget: one state of a short prompt always fits."""
MAX_TOKENS = 1 << 20
"""The largest default budget (a GPU's free memory is not all a reason to pad a batch wider)."""


def token_bytes(model: Any) -> int:
    """Bytes one token of a batch holds at the peak: its keys and values in every layer (`KV_COPIES`
    times) and its activations in one layer (hidden, attention and MLP intermediates)."""
    config = model.config.get_text_config()
    size = model.get_input_embeddings().weight.element_size()
    heads = int(config.num_attention_heads)
    kv_heads = int(getattr(config, "num_key_value_heads", None) or heads)
    head_dim = int(getattr(config, "head_dim", None) or config.hidden_size // heads)
    hidden = int(config.hidden_size)
    inner = int(getattr(config, "intermediate_size", None) or getattr(config, "n_inner", None) or 4 * hidden)
    kv = 2 * int(config.num_hidden_layers) * kv_heads * head_dim * size
    return KV_COPIES * kv + (4 * hidden + 3 * inner) * size


MASK_BUILD_BYTES = 1
"""Bytes an entry of the packed mask holds at the peak beside its own (the compute dtype's): the
bool block `packed_mask` builds it from ([rows, fed, fed], counted over every entry: a bound)."""


def mask_bytes(model: Any, rows: int, fed: int, prefix: int) -> int:
    """Bytes the packed-candidate mask of a batch holds at its peak: `rows` x `fed` x (`prefix` +
    `fed`) entries of the compute dtype, plus `MASK_BUILD_BYTES` each while it is built."""
    size = model.get_input_embeddings().weight.element_size()
    return rows * fed * (prefix + fed) * (size + MASK_BUILD_BYTES)


def mask_tokens(model: Any, rows: int, fed: int, prefix: int) -> int:
    """`mask_bytes` in tokens of the budget (`token_bytes` each), rounded up."""
    return -(-mask_bytes(model, rows, fed, prefix) // token_bytes(model)) if fed else 0


def free_bytes(device: Any) -> int:
    """Memory free now where the model runs: device memory on CUDA, MemAvailable on a CPU."""
    import torch

    device = torch.device(device)
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    import psutil

    return int(psutil.virtual_memory().available)


def default_budget(model: Any, device: Any) -> int:
    """Tokens a batch may hold: `SHARE` of the free memory over `token_bytes`, within bounds."""
    return max(MIN_TOKENS, min(MAX_TOKENS, int(SHARE * free_bytes(device)) // token_bytes(model)))


def context_length(model: Any) -> int | None:
    """The model's context in tokens (its position embeddings), or None where the config has none."""
    value = getattr(model.config.get_text_config(), "max_position_embeddings", None)
    return int(value) if value else None


def token_batches(costs: Sequence[int], max_states: int, budget: int | None,
                  packed: Sequence[tuple[int, int]] | None = None,
                  mask: Callable[[int, int, int], int] | None = None) -> list[list[int]]:
    """Indices grouped into batches, shortest first: at most `max_states` a batch, and (with a
    `budget`) at most `budget` tokens of padded size: count x the widest cost, plus, where `packed`
    gives each state's (prefix, fed) tokens, the tokens of the batch's packed-candidate mask at its
    widest prefix and fed, `mask(rows, fed, prefix)` (`mask_tokens` of the model)."""
    from illm_tools.errors import UsageError

    if max_states < 1:
        raise UsageError("batch_size must be at least 1")
    order = sorted(range(len(costs)), key=costs.__getitem__)
    batches: list[list[int]] = []
    batch: list[int] = []
    prefix = fed = 0  # the batch's widest, were the next state to join
    for i in order:  # sorted: the newest state is the widest of its batch
        if packed is not None:
            prefix, fed = max(prefix, packed[i][0]), max(fed, packed[i][1])
        if batch:
            rows = len(batch) + 1
            padded = rows * costs[i] + (mask(rows, fed, prefix) if packed is not None and mask is not None else 0)
            if len(batch) >= max_states or (budget is not None and padded > budget):
                batches.append(batch)
                batch = []
                prefix, fed = packed[i] if packed is not None else (0, 0)
        batch.append(i)
    if batch:
        batches.append(batch)
    return batches


def describe(lm: Any, widest: int, states: int) -> str:
    """One line: the budget, and the predicted peak of a batch of `states` states of `widest` tokens."""
    per = token_bytes(lm.model)
    weights = sum(p.numel() * p.element_size() for p in lm.model.parameters())
    n = len(token_batches([widest] * states, states, lm.batch_tokens)[0]) if states else 0
    return (f"engine batches: at most {lm.batch_tokens:,} tokens ({lm.batch_tokens * per / 2**30:.2f} GiB at "
            f"{per / 1024:.0f} KiB a token); {n} states of {widest:,} tokens a batch, predicted peak "
            f"{(weights + n * widest * per) / 2**30:.2f} GiB with the weights")
