"""How many threads a process's torch runs on the CPU.

torch's default is one thread per core. Where another process is busy on a core, its
threads wait on one another at every parallel operation: the deposition preview ran 15-30x
slower with two threads and a busy second core than with one (README). So a run that is not
told (``--threads``, or ``OMP_NUM_THREADS`` in its environment) takes the cores that are free
when it starts: the cores it may run on, less the system's load (the 1-minute load average,
rounded), shared among the processes of its own launch on this machine (MPI ranks), at least
one each."""
from __future__ import annotations

import os


def cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # (not Linux)
        return os.cpu_count() or 1


def local_processes() -> int:
    """The processes of this launch on this machine (MPI ranks: MPICH's and Open MPI's
    launchers say so in the environment), 1 otherwise."""
    for var in ("MPI_LOCALNRANKS", "OMPI_COMM_WORLD_LOCAL_SIZE"):
        if os.environ.get(var, "").isdigit():
            return max(int(os.environ[var]), 1)
    return 1


def free_threads(n_cores: int, load: float, processes: int = 1) -> int:
    """Threads per process on ``n_cores`` cores with ``load`` of other work running (the load
    average), shared by ``processes`` processes: at least 1."""
    free = n_cores - int(load + 0.5)
    return max(1, free // max(processes, 1))


def choose(requested: int | None = None) -> tuple[int | None, str]:
    """(threads to set, or None to leave torch's own; why). ``requested``: ``--threads``."""
    if requested is not None:
        return requested, "--threads"
    if os.environ.get("OMP_NUM_THREADS"):
        return None, "OMP_NUM_THREADS"
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):  # (no load average: torch's default)
        return None, "torch's default"
    n, p = cores(), local_processes()
    return free_threads(n, load, p), f"{n} cores, load {load:.1f}" + (f", {p} processes" if p > 1 else "")


def apply(requested: int | None = None) -> str:
    """Set torch's threads as :func:`choose` says; returns a line for the run's cost block."""
    import torch

    n, why = choose(requested)
    if n is not None:
        torch.set_num_threads(n)
    return f"{torch.get_num_threads()} thread(s) per process ({why})"
