"""Runs of a scene: run directories and their lock, checkpoints, the training loop, the scene's plan
(its task resolved and its runs' caps checked once), the runner."""
