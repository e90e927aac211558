"""RunLock under contention: processes that acquire at the same instant never hold it together."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time

from fempdl.app.runs import rundir

# One contender: waits for the go file, then in every round acquires at the round's instant,
# holds the lock for HOLD seconds if it got it, and records (round, acquired, released) or a refusal.
CONTENDER = r"""
import json, sys, time
from pathlib import Path
from fempdl.app.runs.rundir import RunDirectoryError, RunLock
directory, go, out, rounds, slot, hold = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3], *map(float, sys.argv[4:])
Path(out + ".ready").touch()
while not go.exists():
    time.sleep(0.005)
start = float(go.read_text())
records = []
for r in range(int(rounds)):
    instant = start + r * slot
    while time.time() < instant - 0.002:
        time.sleep(0.001)
    while time.time() < instant:
        pass
    lock = RunLock(directory)
    try:
        lock.acquire()
    except RunDirectoryError:
        records.append([r, None, None])
        continue
    acquired = time.time()
    time.sleep(hold)
    released = time.time()
    lock.release()
    records.append([r, acquired, released])
Path(out).write_text(json.dumps(records))
"""


def test_contenders_at_the_same_instant_never_hold_the_lock_together(tmp_path):
    """Four processes, 30 rounds: in every round exactly the intervals of the winners are disjoint, at
    least one wins, and the lock file is gone at the end. (The lock created with O_EXCL and then
    written let a contender read the empty file as stale and delete it: both held it in 8 of 100 trials.)"""
    contenders, rounds, slot, hold = 4, 30, 0.15, 0.05
    directory, go = tmp_path / "run", tmp_path / "go"
    outs = [tmp_path / f"contender{i}.json" for i in range(contenders)]
    procs = [subprocess.Popen([sys.executable, "-c", CONTENDER, str(directory), str(go), str(out), str(rounds),
                               str(slot), str(hold)], env={**os.environ, "OMP_WAIT_POLICY": "PASSIVE"})
             for out in outs]
    try:
        deadline = time.monotonic() + 120
        while not all(os.path.exists(f"{out}.ready") for out in outs):
            assert time.monotonic() < deadline and all(p.poll() is None for p in procs), "a contender died"
            time.sleep(0.05)
        # Written beside and renamed: a contender polling for the go file must never read it half-written.
        staged = tmp_path / "go.staged"
        staged.write_text(repr(time.time() + 0.5))
        os.replace(staged, go)
        assert [p.wait(timeout=120) for p in procs] == [0] * contenders
    finally:
        for p in procs:
            p.kill()
    records = [rec for out in outs for rec in json.loads(out.read_text())]
    refusals = 0
    for r in range(rounds):
        held = sorted((a, b) for rr, a, b in records if rr == r and a is not None)
        refusals += sum(1 for rr, a, _ in records if rr == r and a is None)
        assert held, f"round {r}: nobody took the free lock"
        for (_, end), (begin, _) in zip(held, held[1:]):
            assert begin >= end, f"round {r}: two contenders held the lock together: {held}"
    assert refusals >= rounds            # the contention was real: most rounds refused someone
    assert not (directory / rundir.LOCK).exists()


def test_a_lock_of_a_killed_process_is_taken_over(tmp_path):
    """The kernel frees a dead holder's lock: the next run takes it without waiting."""
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time\n"
                               "from fempdl.app.runs.rundir import RunLock\n"
                               f"RunLock({str(tmp_path)!r}).acquire()\n"
                               "print('held', flush=True)\n"
                               "time.sleep(60)\n"], stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "OMP_WAIT_POLICY": "PASSIVE"})
    try:
        assert holder.stdout.readline().strip() == "held"
        try:
            rundir.RunLock(tmp_path).acquire()
        except rundir.RunDirectoryError as err:
            assert f"in use by another run (process {holder.pid}" in str(err)
        else:
            raise AssertionError("a live holder's lock was taken")
    finally:
        holder.kill()
        holder.wait()
    assert (tmp_path / rundir.LOCK).exists()            # killed: its file stays behind
    with rundir.RunLock(tmp_path):
        assert (tmp_path / rundir.LOCK).read_text().split()[1] == str(os.getpid())
    assert not (tmp_path / rundir.LOCK).exists()
