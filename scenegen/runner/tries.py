"""Every try of a recipe with the proposal it tried: the labelled data of the rejection log, with the
scenes themselves (what the learned verifier trains on: scenegen/diffusion/verifier.py).

:func:`labelled_tries` runs a recipe as :func:`~scenegen.runner.pipeline.run_batch` does (the same
proposals, repairs and order; first passes and repairs through the same workers) and yields each try's
proposal beside its outcome; it writes nothing. It stops when ``n`` scenes were accepted or a cap
(``max_proposals``, ``max_tries``) is spent.
"""

from __future__ import annotations

from collections.abc import Iterator

from scenegen.runner.config import PipelineConfig
from scenegen.runner.executors import LOCAL, Backend, ordered_outcomes
from scenegen.runner.pipeline import make_proposer, proposal_stream
from scenegen.runner.process import Outcome
from scenegen.schema.scene import SceneProposal


def labelled_tries(
    config: PipelineConfig, workers: int = 1, backend: Backend = LOCAL
) -> Iterator[tuple[SceneProposal, Outcome]]:
    """(proposal, outcome) of every try of ``config``'s batch, in index and attempt order."""
    catalog = config.catalog()
    proposer = make_proposer(config, catalog)
    made: dict[tuple[int, int], SceneProposal] = {}

    def remembered(proposals):
        for proposal in proposals:
            made[proposal.index, proposal.attempt] = proposal
            yield proposal

    proposals = remembered(proposal_stream(proposer, config, 0))
    if getattr(config.proposer, "repairs", 0):
        from scenegen.runner.repairing import repaired_outcomes

        def repair(parent, rejection, attempt):
            child = proposer.repair(parent, rejection, attempt)
            if child is not None:
                made[child.index, child.attempt] = child
            return child

        per_index = repaired_outcomes(proposals, config, workers, repair, export=False, backend=backend)
    else:
        per_index = ([o] for o in ordered_outcomes(proposals, config, workers, export=False, backend=backend))
    accepted = tried = 0
    try:
        for outcomes in per_index:
            for outcome in outcomes:
                yield made.pop((outcome.proposal_index, outcome.attempt)), outcome
                tried += 1
                accepted += outcome.record is not None
                if accepted >= config.n or (config.max_tries is not None and tried >= config.max_tries):
                    return
            for key in [k for k in made if k[0] <= outcomes[-1].proposal_index]:
                del made[key]  # tries an accepted sibling made moot
    finally:
        per_index.close()  # stops the workers now, not at garbage collection
