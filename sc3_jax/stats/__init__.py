"""The statistics a world model is judged by, one concept per module, each formula defined once:

    correlation     Pearson r of evaluator against real rates: one vector pair, or a batch of bootstrap draws
    rank_violation  MMRV, the Mean Maximum Rank Violation (SIMPLER's ranking error), the same two shapes
    resample        the bootstrap's resampling: index sets and multiplicities drawn from a seeded numpy Generator
    interval        the percentile interval of bootstrap draws, and a point estimate summarised with it
    floor           the policy-blind floor: the guess an evaluator's r and MMRV must beat
    split_half      the split-half noise ceiling: random halves of the real data, and its point value
    rank_first      P(best): the share of draws in which a policy ranks first, ties split evenly

The bottom floor of the package: pure numpy, no jax, and no import of any other ``sc3_jax`` module
(``tests/test_imports.py`` holds it to that), so the report, diagnostics and training read the same definitions.
"""
