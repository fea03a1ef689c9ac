"""benchmarks/null_condition.py's reading aid: how much of the C2ST the object count explains."""

import numpy as np
from scenes import benchmark


def _layouts(rng, shares, n):
    """Layouts whose only difference between samples is the object count (column 0): the other two
    columns follow the count and noise alike."""
    count = rng.choice(np.arange(2, 2 + len(shares)), size=n, p=shares)
    return np.column_stack([count, count * 0.1 + rng.normal(0, 0.05, n), rng.normal(0, 1, n)]).astype(float)


def test_count_matched_draws_remove_a_difference_that_lies_only_in_the_count():
    """Generated layouts with the wrong count histogram, otherwise as the data: drawn in the data's
    histogram the classifier is at chance, drawn at random it is not, and the draw is as large as the
    scarcest count allows."""
    rng = np.random.default_rng(0)
    data = _layouts(rng, [0.2] * 5, 500)
    generated = _layouts(rng, [0.05, 0.3, 0.4, 0.2, 0.05], 2000)
    result = benchmark("null_condition").count_matched(generated, data, seed=0, draws=2)
    assert 400 <= result["n"] <= 600  # 5 % of 2,000 six-object layouts, a fifth of the draw
    assert result["matched"] < 0.56
    assert result["unmatched"] > result["matched"] + 0.08
