"""Experiments that run the pipeline and measure what comes out: the generator's guidance sweep today;
the closed-loop transfer experiment (issues 18-20) comes here. Above the runner: they use it, nothing
below imports them."""
