"""Drops flung out of the deposition scene, for the escape tests (single process and MPI).

    mpiexec -n 2 python tests/escape_driver.py CASE K1 K2 OUT.npz [section.key=value ...]

runs K1 steps, flings the wire's first six particles out of the scene (:func:`fling`, the
same rows on every rank), runs K2 more and saves the state gathered by id (rank 0)."""
from __future__ import annotations

import sys

import torch


def fling(sim, ids):
    """Make the particles ``ids`` melt drops flung out of the scene: half 3 mm below the
    substrate falling, half 3 mm beside it flying off (their rows on every process alike)."""
    from torchsph.core.state import Phase

    s, box = sim.state, sim.escape
    rows = torch.nonzero(torch.isin(s.id, ids)).squeeze(1)
    below = torch.isin(s.id.index_select(0, rows), ids[: ids.numel() // 2])
    x = s.x.index_select(0, rows).clone()
    x[:, 2] = torch.where(below, torch.full_like(x[:, 2], box.lo[2] - 3e-3), x[:, 2])
    x[:, 1] = torch.where(below, x[:, 1], x[:, 1] + box.hi[1] + 3e-3)
    v = torch.where(below.unsqueeze(1), torch.tensor([0.0, 0.0, -1.0], dtype=x.dtype),
                    torch.tensor([0.0, 1.0, 0.0], dtype=x.dtype))
    s.x[rows], s.v[rows] = x, v
    s.phase[rows], s.body[rows] = int(Phase.FLUID), 0
    sim.fluid_mask = s.phase == Phase.FLUID
    sim.n_fluid = int(sim.fluid_mask.sum())
    sim.stale = True  # the next step is a rebuild point


def run(case, k1, k2, overrides, comm=None):
    from torchsph.io.config import load_case
    from torchsph.run.build import make_simulation
    from torchsph.step.loop import run_steps

    _, cfg = load_case(case, overrides)
    scene, sim = make_simulation(cfg, comm=comm)
    run_steps(sim, steps=k1)
    w0 = scene.info["wire_id0"]
    fling(sim, torch.arange(w0, w0 + 6, dtype=sim.state.id.dtype))
    run_steps(sim, steps=k2)
    return sim


def main(argv):
    import numpy as np

    from parallel.setup import install_abort_hook, make_comm
    from torchsph.io.config import load_case

    case, k1, k2, out, overrides = argv[0], int(argv[1]), int(argv[2]), argv[3], argv[4:]
    install_abort_hook()
    comm = make_comm(load_case(case, overrides)[1])
    sim = run(case, k1, k2, overrides, comm)
    g = comm.gather_owned(sim)
    e = sim.energy_balance()
    n, kg = comm.sum([sim.escape.n, sim.escape.kg])
    if comm.rank == 0:
        np.savez(out, t=sim.t, escaped=np.array([n, kg]), residual=e["residual_rel"],
                 **{k.replace(".", "_"): v for k, v in g.items()})


if __name__ == "__main__":
    main(sys.argv[1:])
