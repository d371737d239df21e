"""The student's answers to a batch of lessons, and how far they are from the teacher's.

One forward pass per batch through the annotator's own engine (`illm_tools.llm.driver.run_batch`, with
autograd on while training): the states' shared prompt part once, then each task's branch, the rest of
its prompt and what is scored after it.

- ranking task (`action`): the student's summed log-probability of each candidate, as the
  annotator sums it; its distribution over the candidates is their softmax (the `sum`
  calibration, the paper's), and the loss is KL(teacher || student), the teacher's distribution
  being the softmax of its own sums (for the oracle: softmax(-2 * steps left)); with
  `ranking_target="argmax"`, the cross-entropy of the teacher's top candidate instead (the one-hot
  target of the paper's Algorithm 1 for f^a: the runner-up earns nothing). The student agrees with
  the teacher where its top candidate is the teacher's.
- text task (`summary`, ...): the mean negative log-likelihood per token of the teacher's text and
  the end-of-text token after it (teacher forcing).

loss = KL or cross-entropy (mean over states) + `text_weight` * NLL (mean over the states' texts).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from illm_tools.distil.lessons import Example

RANKING_TARGETS = ("distribution", "argmax")


@dataclass
class BatchResult:
    """The loss of a batch and the figures behind it."""

    loss: object
    """Scalar tensor (with its graph while training)."""
    ranking_kl: float = 0.0
    """Mean KL(teacher || student) over the batch's ranked states, nats (whatever the ranking target)."""
    text_nll: float = 0.0
    """Mean negative log-likelihood per token of the teacher's texts, nats."""
    agree: int = 0
    """Ranked states whose top candidate is the teacher's."""
    ranked: int = 0
    texts: int = 0
    tokens: int = 0
    """Tokens run through the model."""
    student_best: list[int] = field(default_factory=list)


def example_work(example: Example):
    """A lesson's tokens as the engine's `Work`: its shared prompt part the head, a branch per task."""
    from illm_tools.llm.driver import Work
    from illm_tools.llm.scoring import StatePlan

    return Work(example.shared, branches={b.task: StatePlan(list(b.suffix), [list(c) for c in b.continuations],
                                                            list(b.skip)) for b in example.branches})


def lesson_loss(lm, batch: Sequence[Example], *, text_weight: float = 1.0, grad: bool = False,
                ranking_target: str = "distribution") -> BatchResult:
    """The loss of `batch` for the student `lm` (a `LoadedModel`, its `model` possibly wrapped with
    adapters); `grad`: keep the graph for a backward pass; `ranking_target`: distribution (KL from
    the teacher's) or argmax (cross-entropy of its top candidate)."""
    import torch

    from illm_tools.llm.driver import branch_sums, run_batch

    works = [example_work(e) for e in batch]
    run = run_batch(lm, works, grad=grad)
    kl_terms, rank_terms, nll_terms = [], [], []
    out = BatchResult(loss=None, tokens=sum(e.tokens for e in batch))
    for task, (rows, values) in run.scored.items():
        branches = [next(b for b in batch[i].branches if b.task == task) for i in rows]
        sums = branch_sums(values, [works[i].branches[task] for i in rows])
        if branches[0].kind == "ranking":
            for b, s in zip(branches, sums):
                student = torch.log_softmax(s, dim=0)
                teacher = torch.log_softmax(torch.tensor(b.teacher_logprobs, dtype=student.dtype,
                                                         device=student.device), dim=0)
                kl_terms.append(torch.sum(teacher.exp() * (teacher - student)))
                rank_terms.append(kl_terms[-1] if ranking_target == "distribution" else -student[b.best])
                top = int(torch.argmax(s.detach()))
                out.student_best.append(top)
                out.agree += int(top == b.best)
                out.ranked += 1
        else:
            for b, s in zip(branches, sums):
                scored = len(b.continuations[0]) - b.skip[0]
                nll_terms.append(-s[0] / max(scored, 1))
                out.texts += 1
    zero = torch.zeros((), device=lm.device)
    kl = torch.stack(kl_terms).mean() if kl_terms else zero
    ranking = torch.stack(rank_terms).mean() if rank_terms else zero
    nll = torch.stack(nll_terms).mean() if nll_terms else zero
    out.loss = ranking + text_weight * nll
    out.ranking_kl, out.text_nll = float(kl.detach()), float(nll.detach())
    return out


@dataclass
class Measure:
    """The student's (or its base's) figures over held-out lessons."""

    states: int = 0
    agreement: float = 0.0
    """Share of ranked states whose top candidate is the teacher's."""
    ranking_kl: float = 0.0
    text_nll: float = 0.0
    seconds: float = 0.0

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def measure(lm, examples: Sequence[Example], *, batch_size: int = 8, text_weight: float = 1.0,
            on_progress=None) -> Measure:
    """Agreement with the teacher's top action, KL and text NLL over `examples`, without gradients
    (batches sorted by length, as the annotator batches); `on_progress(n)` after each batch."""
    import time

    from illm_tools.llm.budget import token_batches

    start = time.perf_counter()
    m = Measure(states=len(examples))
    kl = nll = 0.0
    ranked = texts = agree = 0
    for batch in token_batches([e.longest for e in examples], batch_size, None):
        r = lesson_loss(lm, [examples[i] for i in batch], text_weight=text_weight, grad=False)
        kl += r.ranking_kl * r.ranked
        nll += r.text_nll * r.texts
        ranked, texts, agree = ranked + r.ranked, texts + r.texts, agree + r.agree
        if on_progress is not None:
            on_progress(len(batch))
    m.agreement = agree / ranked if ranked else 0.0
    m.ranking_kl = kl / ranked if ranked else 0.0
    m.text_nll = nll / texts if texts else 0.0
    m.seconds = time.perf_counter() - start
    return m
