"""What runs leave behind: the results schema and ``score_vs_law`` (:mod:`.metrics`), atomic output,
manifests and the cache folder (:mod:`.io`). This layer imports nothing else of blf_gym."""
