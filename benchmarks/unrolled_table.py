"""The table bench_unrolled.py prints while it runs: :data:`HEADER`, then :func:`print_row` per configuration."""
from __future__ import annotations

HEADER = (f"{'size':<6}{'dofs':>6} {'solver':<7}{'K':>4}{'B':>4} {'impl s':>8}{'unrl s':>8}{'t u/i':>7} "
          f"{'impl MiB':>9}{'unrl MiB':>9}{'m u/i':>7}{'stored':>8} "
          f"{'petsc s':>8}{'batch s':>8}{'p/b':>6} {'ckpt t/u':>8}{'ckpt m/u':>9} "
          f"{'du':>8}{'dgrad':>8}{'reps':>5}")


def _fmt(value, width: int, spec: str) -> str:
    return f"{'-':>{width}}" if value is None else f"{value:>{width}{spec}}"


def print_row(row: dict, flush: bool = False) -> None:
    t, r, c = row["times_s"], row["ratios"], row["check"]
    mem = row["memory"] or {}
    mi = mem.get("implicit", {}).get("peak_rss_increase_mib")
    mu = mem.get("unrolled", {}).get("peak_rss_increase_mib")
    du = max(c["u_unrolled_vs_implicit"], c["u_unrolled_vs_implicit_petsc"])
    print(f"{row['size']:<6}{row['dofs']:>6} {row['solver']:<7}{row['K']:>4}{row['B']:>4} "
          f"{t['implicit']:>8.3f}{t['unrolled']:>8.3f}{r['time_unrolled_over_implicit']:>7.2f} "
          f"{_fmt(mi, 9, '.1f')}{_fmt(mu, 9, '.1f')}{_fmt(r['memory_unrolled_over_implicit'], 7, '.1f')}"
          f"{row['stored_iterates_mib']:>8.0f} "
          f"{t['implicit_petsc']:>8.3f}{t['implicit_batched']:>8.3f}"
          f"{r['engine_speedup_petsc_over_batched']:>6.2f} "
          f"{_fmt(r.get('checkpointed_time_over_unrolled'), 8, '.2f')}"
          f"{_fmt(r.get('checkpointed_memory_over_unrolled'), 9, '.3f')} "
          f"{du:>8.1e}{c['grad_unrolled_vs_implicit']:>8.1e}{row['repeats']:>5}"
          + ("" if c["forward_agrees"] and c["gradients_agree"] else "  CHECK FAILED"),
          flush=flush)

