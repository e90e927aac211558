"""Floor 4, the training methods: PRDP (progressive refinement of an iteration cap), SIP (physics
inverses fed back through a proxy loss) and HIG (half-inverse gradients). No scenes, no command line."""
