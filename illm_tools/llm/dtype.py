"""Compute dtypes chosen by measurement: `--dtype auto` and the trainer's heads.

Whether bfloat16 is the fast path depends on the machine, not on a flag a program can read
reliably: on this project's 2-core machines a 512x576 by 576x1536 matmul ran at 900 GFLOP/s in
bf16 and 207 in float32 on one AMD EPYC, 0.9 against 29 on another (AVX2 only: bf16 emulated, 33x
slower), and bf16 1.6x slower than float32 on an Intel Xeon with AVX512-BF16. So:

- `resolve_dtype("auto", device)`: on CUDA bfloat16 (bitsandbytes' 4-bit and 8-bit layers compute
  in it too); on a CPU bfloat16 only where `bf16_is_faster` says so, else float32. An
  explicit dtype is returned as it is. Every fingerprint and cache key holds the resolved dtype,
  never "auto", so two machines that resolve differently write different setups (and a run adopts
  its cache's, `illm_tools.rl.adopt`).
- `bf16_is_faster(shape)`: times the matmul in both dtypes (best of 5, a few tens of ms) with the
  current thread count. The answer is cached per machine in `<illm cache>/dtype-probe.json`, keyed by
  the CPU's model name and instruction flags, torch's version, the thread count and the shape, so it
  is measured once per machine (and logged once: what was measured and what was chosen); a changed
  key (another CPU kind after a move, another torch) measures again.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import platform
import time
from pathlib import Path

log = logging.getLogger(__name__)

LLM_SHAPE = (512, 576, 1536)
"""(m, k, n) of the LLM probe: 512 tokens through an MLP projection of SmolLM2-135M's width."""
HEADS_SHAPE = (512, 512, 1024)
"""(m, k, n) of the trainer's probe: a minibatch through one of the iLLM heads' 1024-unit layers."""
PROBE_FILE = "dtype-probe.json"
CHOICES = ("auto", "bfloat16", "float32", "float16")
ISA_LIMITS = ("ATEN_CPU_CAPABILITY", "ONEDNN_MAX_CPU_ISA")
"""Environment variables that limit the instructions torch's kernels use (`ONEDNN_MAX_CPU_ISA=AVX2`
runs a CPU with AMX as one without): part of the probe's key, since they change its answer."""


def cpu_signature() -> str:
    """The CPU's model name and a digest of its instruction flags (Linux /proc/cpuinfo; elsewhere
    the platform's processor string)."""
    model, flags = platform.processor() or platform.machine(), ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and model in ("", platform.machine(), platform.processor()):
                model = value.strip()
            elif key.strip() in ("flags", "Features") and not flags:
                flags = value.strip()
    except OSError:
        pass
    return f"{model} [{hashlib.sha256(' '.join(sorted(flags.split())).encode()).hexdigest()[:12]}]"


def _seconds(dtype, shape: tuple[int, int, int]) -> float:
    import torch

    m, k, n = shape
    a, b = torch.full((m, k), 0.5, dtype=dtype), torch.full((k, n), 0.25, dtype=dtype)  # no RNG use
    a @ b
    best = float("inf")
    for _ in range(5):
        start = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - start)
    return best


def _probe_path() -> Path:
    from illm_tools.llm.loading import cache_root

    return cache_root() / PROBE_FILE


@functools.lru_cache(maxsize=None)
def _measured(key: str, shape: tuple[int, int, int]) -> dict:
    """The probe's record for `key`: read from the machine's file, or measured now and stored."""
    path = _probe_path()
    try:
        known = json.loads(path.read_text())
    except (OSError, ValueError):
        known = {}
    if isinstance(known, dict) and isinstance(known.get(key), dict) and "bf16_faster" in known[key]:
        return known[key]
    import torch

    f32, bf16 = _seconds(torch.float32, shape), _seconds(torch.bfloat16, shape)
    flops = 2 * shape[0] * shape[1] * shape[2]
    record = {"bf16_faster": bf16 < f32, "float32_gflops": flops / f32 / 1e9, "bfloat16_gflops": flops / bf16 / 1e9,
              "measured_unix": time.time()}
    log.info("dtype probe (%s, %d thread%s): a %dx%d by %dx%d matmul runs at %.0f GFLOP/s in bfloat16 and %.0f in "
             "float32: %s is the faster here (measured once, kept in %s)", cpu_signature(), torch.get_num_threads(),
             "s" * (torch.get_num_threads() != 1), shape[0], shape[1], shape[1], shape[2], record["bfloat16_gflops"],
             record["float32_gflops"], "bfloat16" if record["bf16_faster"] else "float32", path)
    try:
        from illm_tools.durable import write_json as _write_json_atomic

        _write_json_atomic(path, {**(known if isinstance(known, dict) else {}), key: record})
    except OSError:  # a read-only home: the answer still holds for this process
        pass
    return record


def bf16_is_faster(shape: tuple[int, int, int] = LLM_SHAPE) -> bool:
    """Whether a bf16 matmul of `shape` beats float32 on this CPU with the current thread count
    (measured once per machine; see the module docstring)."""
    import torch

    isa = "".join(f"|{name}={os.environ[name]}" for name in ISA_LIMITS if os.environ.get(name))
    key = f"{cpu_signature()}{isa}|torch {torch.__version__}|threads {torch.get_num_threads()}|{'x'.join(map(str, shape))}"
    if os.environ.get("ILLM_DTYPE_PROBE"):  # tests and benchmarks simulate a machine: "bfloat16" or "float32"
        return os.environ["ILLM_DTYPE_PROBE"] == "bfloat16"
    return bool(_measured(key, tuple(shape))["bf16_faster"])


def resolve_dtype(dtype: str, device: str = "cpu") -> str:
    """The concrete compute dtype of `dtype` ("auto" resolved as the module docstring says)."""
    from illm_tools.errors import UsageError

    if dtype not in CHOICES:
        raise UsageError(f"--dtype must be one of {', '.join(CHOICES)}, got {dtype!r}")
    if dtype != "auto":
        return dtype
    if str(device).startswith("cuda") or (device == "auto" and _cuda()):
        return "bfloat16"
    return "bfloat16" if bf16_is_faster(LLM_SHAPE) else "float32"


def _cuda() -> bool:
    import torch

    return torch.cuda.is_available()
