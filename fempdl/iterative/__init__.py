"""Floor 2, torch-only K-step maths of a capped solve: unrolled recurrences, CG's reverse pass, fused
Richardson sweeps, the batched engine and sparse operators. Nothing here imports DOLFINx or UFL."""
