"""Setting up a decomposed run: the slab decomposition a case asks for (its halo's parts: search
radius, skin, migration slack) and the abort hook that ends every rank when one fails."""
from __future__ import annotations

import sys
import time
import traceback

from mpi4py import MPI

from parallel.slab import SlabComm


def install_abort_hook(comm=None):
    """An uncaught exception on any rank prints the rank and the error and aborts all ranks
    (no rank is left waiting in a collective)."""
    comm = comm or MPI.COMM_WORLD

    def hook(tp, val, tb):
        sys.stderr.write(f"torchsph rank {comm.Get_rank()}/{comm.Get_size()}: "
                         + "".join(traceback.format_exception(tp, val, tb)))
        sys.stderr.flush()
        time.sleep(0.5)  # let mpiexec forward the message before the abort ends every rank
        comm.Abort(1)

    sys.excepthook = hook


def halo_parts(cfg: dict) -> dict:
    """The halo of a validated case: the search radius, the skin, the neighbour-dependent
    stages of one step (3 search radii; 5 with free-surface forces, 7 with a contact angle)
    and the slack for the motion between migrations; ``halo`` their total (m)."""
    from torchsph.core.kernels import make_kernel

    nm = cfg["numerics"]
    dx = cfg["scene"].get("dx_m")
    if dx is None:  # scenes that give a count instead of a spacing: build once to learn dx
        from torchsph.scenes.builders import build_scene
        dx = build_scene(cfg).dx
    h = nm["h_over_dx"] * dx
    kernel = make_kernel(nm["kernel"], cfg["scene"]["dim"])
    skin = nm["skin_over_dx"] * dx
    stages = 3
    if "surface" in cfg:  # colour -> normals -> smoothed normals -> curvature -> force
        stages = 5
        if cfg["surface"].get("contact_angle_deg") is not None and cfg["surface"].get("wetting", True):
            stages = 7  # the contact line reads the curvature beside it, and spreads its force
    slack = nm.get("migration_slack_over_skin", 4.0)
    search = kernel.radius(h) + skin
    return {"search": search, "skin": skin, "stages": stages, "slack_skins": slack,
            "halo": stages * search + skin * (1.0 + slack)}


def make_comm(cfg: dict, comm=None) -> SlabComm:
    """A SlabComm for a validated case (:func:`halo_parts`)."""
    hp = halo_parts(cfg)
    return SlabComm(hp["search"], hp["skin"], stages=hp["stages"], comm=comm,
                    rebalance_every=cfg["numerics"].get("rebalance_every", 0), slack_skins=hp["slack_skins"])
