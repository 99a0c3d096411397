"""What every compiled function rests on: the import closures that key the compiled caches
(:mod:`.sources`), the kernel's libm-free maths (:mod:`.vmath`), its constant-length views
(:mod:`.views`) and the one declaration of every packed array's layout (:mod:`.layout`). This
layer imports nothing else of blf_gym."""
