"""The decision: which verified poses are refined, which refined pose is the answer, which are
its alternatives, and when a more confident alternative takes the answer's place.

It works over immutable records of one search round: :class:`Found` (a verified pose and the
search it was found under) and :class:`Refined` (that pose after ICP, scored again, with its
fit). It refines and finishes nothing itself: :func:`decide` is handed the engine's ``refine``
and ``finish`` (both once per pose and request, through
:class:`~catalign.registration.stages.request.RequestCache`), so the rules below can be tested on
hand-made records.

1. The ``refine`` best matched poses are refined, and the best pose of each further distinct
   answer (another model, or the same one turned more than 30 degrees: the alternatives).
2. Unless one of them fits surely (``sure_fitness``), so are the ``sweep_refine`` best distinct
   swept answers and the best swept pose under each orientation, kept only if they then fit
   exactly (``exact_fitness``): a view of a chair's underside can fit its own CAD exactly turned
   the wrong way, and the sweep finds the right turn. A swept pose of another instance fits
   that surface without matching its parts, and measured a worse category-level pose than the
   matched ones, so the others are dropped.
3. The answer is the best-scored pose that fits surely, else exactly (the observed instance
   itself), else the best of the refined best matches; among those that fit, only the ones
   within ``fit_margin`` of the closest fit compete (a near twin of the observed chair fits its
   view surely too, but not as closely as the chair's own model). Its alternatives are the
   other distinct refined answers, best first.
4. Each answer is finished (its category fit and confidence); an alternative more confident
   than an answer that does not fit exactly by over ``confidence_margin`` takes its place if it
   still is once finished as the answer was (refitted at the observed size).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from catalign.registration.decision.answers import SymmetryOf, distinct, no_symmetry, promoted
from catalign.registration.decision.confidence import Evidence
from catalign.registration.stages.refine import Fit
from catalign.registration.stages.search import Search
from catalign.registration.stages.verify import Scored


@dataclass(frozen=True, eq=False)
class Found:
    """A verified pose (its score weighed by the beliefs in its orientation) and the search it
    was found under."""

    search: Search
    scored: Scored

    @property
    def swept(self) -> bool:
        return self.scored.hypothesis.swept


@dataclass(frozen=True, eq=False)
class Refined:
    """A found pose refined by ICP: the refined pose scored again (weighed the same way), the
    three factors of its unweighed score (explained, covered, layout) and its fit."""

    found: Found
    scored: Scored
    parts: tuple[float, float, float]
    fit: Fit

    @property
    def search(self) -> Search:
        return self.found.search


@dataclass(frozen=True, eq=False)
class Finished:
    """An answer made final: where it was found, its pose (after the category fit) and score,
    its fit, the evidence its confidence was read from, and that confidence."""

    search: Search
    item: Scored
    fit: Fit
    evidence: Evidence
    confidence: float | None


@dataclass(frozen=True, kw_only=True)
class Rules:
    """The decision's options, as :class:`~catalign.registration.config.EngineConfig` names
    them."""

    refine: int
    alternatives: int
    sweep_refine: int
    exact_fitness: float
    sure_fitness: float
    confidence_margin: float | None
    fit_margin: float | None = None


@dataclass(frozen=True, eq=False)
class Decision:
    """The finished answers, the winner first, and every pose tried (the refined ones and the
    matched ones that were not refined): the evidence's margins and the candidates' scores are
    read from them."""

    answers: tuple[Finished, ...]
    tried: tuple[Scored, ...]

    @property
    def winner(self) -> Finished:
        return self.answers[0]

    def fits_exactly(self, exact_fitness: float) -> bool:
        """Whether the winner fits the query as only the observed instance itself does."""
        return self.winner.fit.fitness >= exact_fitness

    def weak(self, fallback: float) -> bool:
        """Whether the winner is less confident than ``fallback`` (always, without a
        calibrator)."""
        confidence = self.winner.confidence
        return confidence is None or confidence < fallback


Refine = Callable[[Found], Refined]
Finish = Callable[[Refined, Sequence[Scored], bool], Finished]


def decide(
    found: Sequence[Found],
    rules: Rules,
    *,
    refine: Refine,
    finish: Finish,
    symmetry_of: SymmetryOf = no_symmetry,
) -> Decision | None:
    """The answer to one search round from its verified poses ``found`` (best first); None
    when nothing was found. ``refine`` gives a found pose's :class:`Refined`, ``finish`` a
    refined answer's :class:`Finished` (against the poses tried; refitted at the observed size
    when its last argument is true); ``symmetry_of`` a model's symmetry, under whose turns two
    poses are one answer."""
    if not found:
        return None
    matched = [item for item in found if not item.swept] or list(found)
    refined, best = _refined(matched, found, rules, refine, symmetry_of)
    ranked = ranked_answers(refined, best, rules, symmetry_of)
    sources = {id(r.found.scored) for r in refined}
    tried = [r.scored for r in refined]
    tried += [item.scored for item in matched if id(item.scored) not in sources]
    finished = [finish(r, tried, rank == 0) for rank, r in enumerate(ranked)]
    return Decision(tuple(_promoted(finished, ranked, tried, rules, finish)), tuple(tried))


def _refined(
    matched: list[Found],
    found: Sequence[Found],
    rules: Rules,
    refine: Refine,
    symmetry_of: SymmetryOf,
) -> tuple[list[Refined], list[Refined]]:
    """Steps 1 and 2 of the module docstring: the refined poses, and among them the refined
    best matches (the winner when nothing fits exactly)."""
    leading = matched[: rules.refine]
    leading += [
        item
        for item in distinct(matched, 1 + rules.alternatives, _scored, symmetry_of)
        if not any(item is chosen for chosen in leading)
    ]
    refined = [refine(item) for item in leading]
    best = refined[: min(rules.refine, len(matched))]
    if not any(_fits(r, rules.sure_fitness) for r in refined):
        for item in swept_to_refine(found, rules.sweep_refine, symmetry_of):
            done = refine(item)
            known = any(done.scored is r.scored for r in refined)
            if _fits(done, rules.exact_fitness) and not known:
                refined.append(done)
    return refined, best


def _promoted(
    finished: list[Finished],
    ranked: list[Refined],
    tried: list[Scored],
    rules: Rules,
    finish: Finish,
) -> list[Finished]:
    """Step 4 of the module docstring: ``finished`` (the winner first), with an alternative
    clearly more confident than a winner that does not fit exactly in the winner's place, if it
    still is once refitted as the winner was."""
    if finished[0].fit.fitness >= rules.exact_fitness:
        return finished
    first = promoted([f.confidence for f in finished], rules.confidence_margin)
    if not first:
        return finished
    challenger = finish(ranked[first], tried, True)
    if not promoted([finished[0].confidence, challenger.confidence], rules.confidence_margin):
        return finished
    return [challenger, *finished[:first], *finished[first + 1 :]]


def ranked_answers(
    refined: Sequence[Refined],
    best: Sequence[Refined],
    rules: Rules,
    symmetry_of: SymmetryOf = no_symmetry,
) -> list[Refined]:
    """The distinct answers among ``refined``, the winner first (step 3 of the module
    docstring): the best-scored of those that fit surely, else exactly (of those, the ones
    within ``fit_margin`` of the closest fit), else of ``best``; the rest by score, at most
    ``1 + alternatives`` in all. Ties keep the order given."""
    exact = [r for r in refined if _fits(r, rules.exact_fitness)]
    exact = [r for r in exact if _fits(r, rules.sure_fitness)] or exact
    if exact and rules.fit_margin is not None:
        closest = max(r.fit.fitness for r in exact)
        exact = [r for r in exact if _fits(r, closest - rules.fit_margin)]
    winner = max(exact or best, key=lambda r: r.scored.score)
    rest = sorted((r for r in refined if r is not winner), key=lambda r: -r.scored.score)
    return distinct([winner, *rest], 1 + rules.alternatives, lambda r: r.scored, symmetry_of)


def swept_to_refine(
    found: Sequence[Found], sweep_refine: int, symmetry_of: SymmetryOf = no_symmetry
) -> list[Found]:
    """The ``sweep_refine`` best distinct swept poses among ``found`` (best first), and the
    best swept pose under each orientation: a proposed up believed little weighs its poses
    down, yet the observed instance fits exactly under it when it is the right one."""
    swept = [item for item in found if item.swept]
    chosen = distinct(swept, sweep_refine, _scored, symmetry_of)
    for search in dict.fromkeys(item.search for item in swept):
        best = next(item for item in swept if item.search is search)
        if not any(best is item for item in chosen):
            chosen.append(best)
    return chosen


def _fits(refined: Refined, fitness: float) -> bool:
    return refined.fit.fitness >= fitness


def _scored(item: Found) -> Scored:
    return item.scored
