"""Floor 2, the K-step maths of a capped solve in torch: unrolled recurrences, CG's reverse pass, fused
Richardson sweeps, the batched engine and sparse operators. Nothing here imports DOLFINx or UFL; only the
batched engine (``batched.py``) touches PETSc: it reads the assembled matrix and the ``KSPOptions`` of
the solve it runs in torch instead."""
