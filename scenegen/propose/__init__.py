"""Proposers: (condition, n, seed) -> scene proposals. See :mod:`scenegen.propose.base`."""
