"""Command line: ``python -m torchsph CASE_DIR [options]``."""
from __future__ import annotations

import argparse
import copy
import os
import sys
from pathlib import Path

from torchsph.io.checkpoint import CheckpointError
from torchsph.io.config import CaseError, load_case
from torchsph.io.snapshots import OutputError
from torchsph.step.simulation import SimulationError, UnstableStepError


def parse_args(argv=None):
    ap = argparse.ArgumentParser(prog="python -m torchsph",
                                 description="Run a torchsph case (a folder with case.toml). Every run prints what it costs before it steps; --estimate prints only that.")
    ap.add_argument("case", help="case folder, e.g. cases/taylor_green_2d")
    ap.add_argument("--out", type=Path, default=None, help="output folder (default CASE_DIR/output)")
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--t-end", type=float, default=None, help="simulated end time, s")
    g.add_argument("--steps", type=int, default=None, help="number of steps")
    ap.add_argument("--device", choices=("cpu", "cuda"), default=None)
    ap.add_argument("--dtype", choices=("float32", "float64"), default=None)
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="override a case key (TOML value), repeatable")
    ap.add_argument("--compile", action="store_true",
                    help="fuse the pair loops with torch.compile (same as --set numerics.compile=true)")
    ap.add_argument("--preview", action="store_true",
                    help="run the case's coarse, short [preview] variant (minutes on a laptop CPU)")
    ap.add_argument("--no-skip", action="store_true",
                    help="skip nothing: every particle every step, cold solid included (same as --set "
                         "numerics.skip_cold_solid=false)")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    ap.add_argument("--checkpoint-every", type=int, default=None, metavar="N",
                    help="write OUT/checkpoint.pt every N steps (always at the end and on Ctrl-C)")
    go_on = ap.add_mutually_exclusive_group()
    go_on.add_argument("--restart", type=Path, default=None, metavar="CHECKPOINT",
                       help="continue a run from its checkpoint (same case; [run] may differ)")
    go_on.add_argument("--branch", type=Path, default=None, metavar="CHECKPOINT",
                       help="go on from a checkpoint's state with this case's physics, which may differ from "
                            "the checkpoint's in any key but those that build the scene (a what-if from a "
                            "developed state, e.g. --set surface.marangoni=false); the changed keys are printed "
                            "and recorded in summary.json")
    ap.add_argument("--threads", type=int, default=None, metavar="N",
                    help="torch's CPU threads per process (default: the cores free when the run starts, "
                         "shared among the MPI ranks on this machine; OMP_NUM_THREADS, where set, decides)")
    ap.add_argument("--estimate", action="store_true",
                    help="print what the run costs (particles, memory, steps, disk, and the wall time "
                         "projected from a probe of its first steps) and exit; writes nothing")
    return ap.parse_args(argv)


def mpi_size() -> int:
    """Number of processes when launched by mpirun / mpiexec (MPICH, Open MPI), else 1;
    read from the launcher's environment so that one process never imports MPI."""
    for var in ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "MPI_LOCALNRANKS"):
        if os.environ.get(var, "").isdigit():
            return int(os.environ[var])
    return 1


def _rank_tag() -> str:
    if mpi_size() > 1:
        from mpi4py import MPI
        return f" (rank {MPI.COMM_WORLD.Get_rank()})"
    return ""


def _abort_others(code: int) -> int:
    """Under mpirun an error on one rank must not leave the others waiting in a collective."""
    if mpi_size() > 1:
        from mpi4py import MPI
        sys.stderr.flush()
        MPI.COMM_WORLD.Abort(code)
    return code


def _global_checkpoint(path) -> bool:
    """A checkpoint written by an MPI run (it restarts on any number of ranks, one included)."""
    if path is None or not Path(path).exists():
        return False
    from torchsph.io.checkpoint import read
    return read(path).get("format") == "global-1"


def check_out(out: Path, what: str):
    """The output folder exists (made if need be) and is writable; else a one-line CaseError."""
    if out.exists() and not out.is_dir():
        raise CaseError(f"{what} {out}: is a file, not a folder (give a folder for the run's output)")
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".torchsph-write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise CaseError(f"{what} {out}: cannot write there ({e.strerror or e}); give a writable folder") from None


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        if args.t_end is not None and args.t_end <= 0:
            raise CaseError(f"--t-end {args.t_end}: must be > 0")
        if args.steps is not None and args.steps <= 0:
            raise CaseError(f"--steps {args.steps}: must be > 0")
        if args.threads is not None and args.threads <= 0:
            raise CaseError(f"--threads {args.threads}: must be > 0")
        overrides = (args.overrides + (["numerics.compile=true"] if args.compile else [])
                     + (["numerics.skip_cold_solid=false"] if args.no_skip else []))
        path, cfg = load_case(args.case, overrides, preview=args.preview)
        out = args.out if args.out is not None else path.parent / ("output_preview" if args.preview else "output")
        if not args.estimate:
            check_out(out, "--out" if args.out is not None else "the output folder")
        from torchsph.run.runner import run_case
        if args.checkpoint_every is not None and args.checkpoint_every <= 0:
            raise CaseError(f"--checkpoint-every {args.checkpoint_every}: must be > 0")
        from torchsph.run import threads
        restart = args.restart if args.branch is None else args.branch
        kw = dict(t_end=args.t_end, steps=args.steps, device=args.device, dtype=args.dtype,
                  progress=not args.quiet, checkpoint_every=args.checkpoint_every, restart=restart,
                  estimate=args.estimate, threads=threads.apply(args.threads), branch=args.branch is not None)
        runner = run_case
        if mpi_size() > 1 or _global_checkpoint(restart):
            from parallel.run import run_case_mpi as runner  # launched by mpirun / mpiexec
        if not args.estimate and not args.quiet:
            # the cost before the run: a probe of a throw-away copy at the step the run will
            # spend its steps in (the first steps of a run that will melt are not representative)
            runner(copy.deepcopy(cfg), path, out, **{**kw, "estimate": True})
        s = runner(cfg, path, out, **kw, announce=args.estimate)
        if s is None or args.estimate:  # not rank 0, or only the estimate
            return 0
    except (CaseError, CheckpointError) as e:
        print(f"torchsph: error: {e}", file=sys.stderr)
        return _abort_others(2)
    except UnstableStepError as e:  # a refused numerics.dt_s is bad input, not a blow-up
        print(f"torchsph: error: {e}", file=sys.stderr)
        return _abort_others(2)
    except SimulationError as e:
        ck = out / "checkpoint.pt"
        hint = (f"; the last checkpoint is {ck}: go on from it with --restart {ck} (and, past a blow-up, "
                f"a smaller step: --set numerics.cfl=...)") if ck.exists() else ""
        print(f"torchsph: stopped{_rank_tag()}: {e}{hint}", file=sys.stderr)
        return _abort_others(3)
    except OutputError as e:  # a full disk, a lost mount: the files it would replace are as they were
        ck = out / "checkpoint.pt"
        hint = (f"; the last checkpoint {ck} is intact: make room and go on with --restart {ck}" if ck.exists()
                else "; no checkpoint was written yet")
        print(f"torchsph: stopped{_rank_tag()}: {e}{hint}", file=sys.stderr)
        return _abort_others(4)
    except KeyboardInterrupt as e:
        print(f"torchsph: {e or 'interrupted'}", file=sys.stderr)
        return 130
    legs = (f"{s['steps_last_leg']} steps in {s['wall_last_leg_s']:.2f} s (this leg; {s['steps']} steps, "
            f"{s['wall_s']:.2f} s in all)" if s["steps_last_leg"] != s["steps"] else
            f"{s['steps']} steps in {s['wall_s']:.2f} s")
    print(f"torchsph: {legs} to t = {s['t_final_s']:.6g} s, {s['n_particles']} particles, "
          f"{s['particle_steps_per_s']:.3g} particle-steps/s ({s['active_particle_steps_per_s']:.3g} of the "
          f"integrated particles), dt bound by {s['dt_binding_limit']}"
          + (f", Mach {s['mach_max']:.3f}" if s["mach_max"] is not None else "") + f"; output in {out}")
    e = s.get("energy") or {}
    if e:
        flows = ", ".join(f"{k[:-2]} {v:+.4g} J" for k, v in e.items() if k.endswith("_J") and k != "residual_J")
        print(f"torchsph: energy: {flows}; balance residual {e['residual_J']:.3g} J "
              f"({e['residual_rel']:.2g} of the flows)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
