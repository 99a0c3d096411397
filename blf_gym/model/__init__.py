"""The plant and its task: parameters and presets (:mod:`.params`, the one place defaults live),
the n-link rigid-body dynamics (:mod:`.dynamics`), the uncertainties (:mod:`.uncertainty`: friction,
dead zone, external force), the reference (:mod:`.reference`) and the time-varying bounds
(:mod:`.bounds`). Compiled helpers here import only :mod:`blf_gym.jit`."""
