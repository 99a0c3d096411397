"""The Gymnasium side: the protocol's suites and seeds (:mod:`.protocol`), the logic the single and vector envs share (:mod:`.envcore`), the envs
(:mod:`.env`, :mod:`.vector`), the observation's table (:mod:`.observation`), the scenario knobs
and suites (:mod:`.scenarios`), the difficulty levels (:mod:`.levels`), the look-ahead hand-back
(:mod:`.lookahead`), rendering (:mod:`.render`) and Safety-Gymnasium's six-value step
(:mod:`.safety`)."""
