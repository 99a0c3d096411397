"""What every compiled function rests on: the import closures that key the compiled caches
(:mod:`.sources`), the kernel's libm-free maths (:mod:`.vmath`) and its constant-length views
(:mod:`.views`). This layer imports nothing else of blf_gym."""
