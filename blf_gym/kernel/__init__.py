"""The compiled closed loop: the kernel's generator, its build and cache, and
:class:`~blf_gym.kernel.simulate.ClosedLoop` (:mod:`.simulate`), the status and last-signal layouts
(:mod:`.status`) and the reward's terms and per-sample sums (:mod:`.reward`)."""
