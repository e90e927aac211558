"""Constants measured on the project's machines (2 cores), each beside the benchmark that sets it.

They decide speed, never results: which engine runs a batch, how many columns share a pass over a
matrix, when a second torch thread pays, and which solves get a Ctrl-C check. Re-measure them with
the named script on a new kind of machine; the committed JSON of each run is in ``bench-results/``.
"""

# --- the batched engine's rule against PETSc's one-solve-per-sample loop (KSPOptions(engine="auto"))
#: Richardson runs batched from this batch size: faster at 4k and 66k DOFs, on one thread and on two
#: (benchmarks/bench_floor.py).
RICHARDSON_MIN_BATCH = 2
#: CG runs batched from this batch size: the smallest where batched CG beat PETSc's loop
#: (benchmarks/bench_krylov.py). GMRES never runs batched by default: its batched Gram-Schmidt streams
#: B Krylov bases from memory where PETSc's one basis stays in cache (same script).
CG_MIN_BATCH = 8

# --- column groups: a group's iterates stay in cache, at the price of reading the matrix once per group
#: Columns per group and torch thread of the fused Richardson sweeps (benchmarks/bench_floor.py: best at
#: 66k DOFs on 1 and 2 threads).
SWEEP_GROUP = 8
#: Columns per group of batched CG (benchmarks/bench_krylov.py: best at 4k and 66k DOFs).
CG_GROUP = 8
#: Below this many multiply-adds per sparse product (nonzeros x group width), one torch thread is
#: faster than two: 4k and 16k DOFs ran faster on one, 66k on two (benchmarks/bench_floor.py).
PARALLEL_MIN_WORK = 2_000_000

# --- interruptible PETSc solves
#: Solves whose cap (or PETSc's converged-solve cap when uncapped) times the number of unknowns
#: reaches this get a Python KSP monitor, so that Ctrl-C stops them within an iteration: about 0.3 s
#: of Richardson-Jacobi iterations or more. The monitor costs 0.2-0.7 us per iteration
#: (benchmarks/bench_bounds.py), which only matters for small, short solves, and those go without it.
INTERRUPT_CHECK_MIN_WORK = 10 ** 8

# --- a Newton solve's lagged factorisation (KSPOptions.preset("lu-lagged"))
#: A solve preconditioned by an earlier Jacobian's LU that needs more GMRES iterations than this sets
#: the LU up again on the current matrix. At 9k DOFs an iteration (a product and two triangular
#: solves) costs about an eighth of a factorisation; over a 100-step nonlinear heat rollout 3 was the
#: fastest of 2, 3, 5 and 8 (10.3 s against 10.8, 10.4 and 12.2 s: benchmarks/bench_rollout.py).
LAGGED_REFRESH_ITERATIONS = 3
