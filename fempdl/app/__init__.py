"""Floor 5, the scene application and the ``fempdl`` command. Its rooms, in import order (a room
imports only the ones before it): ``schema`` (scene sections, task declarations) -> ``tasks/`` (one
module per task, one registry) -> ``scene`` (parse and validate scene files) -> ``runs/`` (run
directories, checkpoints, the trainer, the runner) -> ``reports/`` (trade-off and method comparisons)
-> ``cli``."""
