"""Runs of a scene: run directories and their lock, checkpoints, the training loop, the runner."""
