"""Torch-side K-step maths of the capped solve: the unrolled recurrences, the batched engine, sparse operators and the unrolled layer path (no UFL)."""
