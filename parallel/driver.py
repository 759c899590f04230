"""Run a case for a number of steps on the MPI ranks and save the state gathered by
particle id (rank 0), for comparing decomposed runs with the single-process run.

    mpiexec -n 2 python -m parallel.driver CASE STEPS OUT.npz [section.key=value ...]
"""
from __future__ import annotations

import sys

import numpy as np

from torchsph.io.config import load_case
from torchsph.run.build import make_simulation
from torchsph.step.loop import run_steps

from .setup import install_abort_hook, make_comm


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    case, steps, out, overrides = argv[0], int(argv[1]), argv[2], argv[3:]
    install_abort_hook()
    _, cfg = load_case(case, overrides)
    comm = make_comm(cfg)
    _, sim = make_simulation(cfg, comm=comm)
    run_steps(sim, steps=steps)
    g = comm.gather_owned(sim)
    e = sim.energy_balance()
    if comm.rank == 0:
        np.savez(out, t=sim.t, step=sim.step, energy=np.array([e.get("stored_J", 0.0), e.get("residual_J", 0.0)]),
                 imbalance=np.array(comm.imbalance or [1.0]), migrations=comm.n_migrations, kept=comm.n_kept,
                 **{k.replace(".", "_"): v for k, v in g.items()})


if __name__ == "__main__":
    main()
