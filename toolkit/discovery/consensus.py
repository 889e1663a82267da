"""Discovery over several runs of the same scene: do their decisions agree?

Stage 0 on a GPU is not bit-reproducible (atomic accumulation order), and the geometry it gives,
the base fit and the candidates' refits move with it. On the full-size benchmark from images a
scene's decision changed between two runs more often than not (of 8 scenes whose effect the data
show in both runs, 1 was named in both, 5 in at least one: ``docs/tutorials/discovery.md``). So a
name is worth checking on a second run of the scene (``projo4d run --seed 1``), and
``projo4d discover RUN_A RUN_B`` runs discovery on each and reports :func:`consensus`:

* every run names the same effect: that name, with the union of the candidates each run could
  not tell apart from it;
* no run finds a missing effect: none;
* some runs name an effect and the others find none: the effect is near what the clip can show,
  not named;
* the runs name different effects: not named; the names, how many runs chose each, and what each
  run said would separate its tied candidates.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Optional, Sequence

__all__ = ["Consensus", "consensus", "consensus_markdown"]


@dataclass
class Consensus:
    """The decisions of several discovery runs of one scene.

    Attributes:
        runs: the run folders (or labels), in the order given.
        decisions: each run's decision (``None``: no missing effect; ``"camera_pose"``: an
            observation problem).
        agreed: every run made the same decision.
        decision: that decision when they agree, else ``None``.
        counts: how many runs made each decision (``"none"`` for no missing effect).
        tied: candidates some run could not tell apart from its decision (union over runs).
        separation: the runs' sentences on what would separate tied candidates (deduplicated).
        sentence: one sentence for a person.
    """

    runs: list[str]
    decisions: list[Optional[str]]
    agreed: bool
    decision: Optional[str]
    counts: dict[str, int]
    tied: list[str] = field(default_factory=list)
    separation: list[str] = field(default_factory=list)
    sentence: str = ""

    def to_dict(self) -> dict:
        return {"runs": list(self.runs), "decisions": list(self.decisions), "agreed": self.agreed, "decision": self.decision,
                "counts": dict(self.counts), "tied": list(self.tied), "separation": list(self.separation),
                "sentence": self.sentence}


def consensus(results: Sequence[dict], runs: Sequence[str]) -> Consensus:
    """Whether the discovery results of several runs of one scene agree.

    Args:
        results: each run's ``discovery.json`` (:meth:`toolkit.discovery.DiscoveryResult.to_dict`):
            ``decision``, ``indistinguishable`` and ``separation`` are read.
        runs: a label per result (its run folder), in the same order.

    Raises:
        ValueError: fewer than two results, or not one label per result.
    """
    if len(results) < 2:
        raise ValueError(f"a consensus needs at least two runs, got {len(results)}")
    if len(runs) != len(results):
        raise ValueError(f"{len(results)} results but {len(runs)} run labels")
    decisions = [r.get("decision") for r in results]
    counts = Counter("none" if d is None else d for d in decisions)
    n = len(results)
    agreed = len(counts) == 1
    decision = decisions[0] if agreed else None
    tied = sorted({t for r, d in zip(results, decisions) for t in (r.get("indistinguishable") or []) if t != d})
    separation = list(dict.fromkeys(s["sentence"] for r in results for s in (r.get("separation") or []) if s.get("sentence")))
    if agreed and decision is None:
        sentence = f"No run finds a missing effect ({n} runs)."
    elif agreed:
        what = "an observation problem (camera pose)" if decision == "camera_pose" else decision
        sentence = f"All {n} runs name {what}."
        if tied:
            sentence += f" Some runs could not tell it apart from {', '.join(tied)}."
    elif set(counts) - {"none"} and len(set(counts) - {"none"}) == 1:
        name = next(k for k in counts if k != "none")
        sentence = (f"{name} is named in {counts[name]} of {n} runs and no effect in the others: it is near what this clip "
                    "can show, so it is not named. A longer clip, another camera or another throw would settle it.")
    else:
        names = ", ".join(f"{k} ({v} of {n} runs)" for k, v in counts.most_common())
        sentence = (f"The runs disagree: {names}. Stage 0's run-to-run variation is enough to change the answer, so none is "
                    "named; they are the candidates to separate.")
    return Consensus(runs=[str(r) for r in runs], decisions=decisions, agreed=agreed, decision=decision, counts=dict(counts),
                     tied=tied, separation=separation, sentence=sentence)


def consensus_markdown(c: Consensus, verdicts: Optional[Sequence[str]] = None) -> str:
    """A short report: the sentence, then each run's decision (and verdict, when given)."""
    lines = ["# Discovery over several runs", "", c.sentence, "", "| run | decision |", "|---|---|"]
    for run, d in zip(c.runs, c.decisions):
        lines.append(f"| {run} | {'no missing effect' if d is None else d} |")
    if c.separation:
        lines += ["", "What would separate tied candidates, as the runs said:", ""] + [f"- {s}" for s in c.separation]
    if verdicts:
        lines += ["", "Each run's verdict:", ""] + [f"- `{run}`: {v}" for run, v in zip(c.runs, verdicts)]
    return "\n".join(lines) + "\n"
