"""Recovery policies: grasp primitives, expert labels and the baseline policy (issue 19 lands here)."""
