"""The plant and its task: parameters and presets (:mod:`.params`, the one place defaults live),
the n-link rigid-body dynamics (:mod:`.dynamics`), the uncertainties (:mod:`.uncertainty`: friction,
dead zone, external force), the reference (:mod:`.reference`) and the time-varying bounds
(:mod:`.bounds`); the task family of 2 to 7 links (:mod:`.family`). Compiled helpers here import only :mod:`blf_gym.jit`."""
