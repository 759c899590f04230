"""The deposition step against a reference commit (``python scripts/tools/bench.py --deposition``).

Both codes are measured one after the other, 1 thread, each in its own process
(``scripts/tools/bench_deposition_driver.py``): the reference commit (default b14e316) is checked out into a
temporary git worktree and removed afterwards. States:

- **preview, t = 0.03 s**: ``cases/perpendicular_350W --preview`` run to t = 0.03 s by the
  reference code (melt, fed wire, the active set), its checkpoint cached under
  ``~/.cache/torchsph-bench/<commit>``; both codes restart from that one state (the flow
  is chaotic: states run by each code differ by 20 ms, and so does their cost), rebuild
  their neighbour lists, take 5 warm-up steps and ``--steps`` timed steps. This code also
  runs the preview to t = 0.03 s itself (cached by its commit and a hash of its diff), for
  the table of the highest temperature and melt volume at 10 and 20 ms.
- **full, first steps**: ``cases/perpendicular_350W`` at dx = 0.1 mm (733 600 particles) built
  afresh, steps 2..11 counted for host syncs, then ``--full-steps`` timed steps.
- **full, developed** (``--t-developed``, default 3 ms: 14 melt particles, the melt's acoustic
  step limit, the heated zone grown over 510 steps): the full scene run to that time by the
  reference code, its checkpoint cached as the preview's (the reference takes ~15 min for it,
  once); both codes restart from it as from the preview state, then ``--full-steps`` timed steps.

The preview state is measured ``--repeat`` times (default 3), the two codes taking turns, and
each code's median round is shown (the rounds' speed-ups are printed above the table): a load
elsewhere on the machine moves single rounds by up to 30 %.

Columns: ms per step over the timed steps (rebuilds included), the median plain step, the
extra cost of a step that rebuilds the neighbour list (all of them, then split into those that kept
the active set and those that refreshed it, as the heated zone reached its edge), particle-steps/s, the process's peak
RSS, host synchronisations per step (without and with a rebuild; :mod:`torchsph.core.syncs`), and
the reference's time over this code's.
"""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DRIVER = ROOT / "scripts" / "tools" / "bench_deposition_driver.py"
CACHE = Path(os.environ.get("TORCHSPH_BENCH_CACHE", Path.home() / ".cache" / "torchsph-bench"))


def git(*args, cwd=ROOT) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


def tree_key(tree: Path) -> str:
    """The commit, plus a hash of the uncommitted changes to the code and the cases."""
    head = git("rev-parse", "--short=12", "HEAD", cwd=tree)
    diff = git("diff", "HEAD", "--", "torchsph", "parallel", "cases", cwd=tree)
    return head + ("-" + hashlib.sha256(diff.encode()).hexdigest()[:8] if diff else "")


def env1():
    return {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def same_model(tree: Path) -> list[str]:
    """--set arguments that put a tree on the reference's physics: a version with the wetting
    model runs these comparisons without it (the thesis's c = 1 in melt and solid, as b14e316),
    and one whose case names [solid_contact] without that term (b14e316 has none)."""
    config = next(p for p in (tree / "torchsph" / "io" / "config.py", tree / "torchsph" / "config.py") if p.exists())
    has = '"wetting": Key(' in config.read_text()
    contact = "[solid_contact]" in (tree / "cases" / "perpendicular_350W" / "case.toml").read_text()
    return (["--set", "surface.wetting=false"] if has else []) + (["--set", "solid_contact.enabled=false"] if contact else [])


def preview_checkpoint(tree: Path, t: float) -> Path:
    out = CACHE / tree_key(tree) / f"preview_t{t:g}"
    ck = out / "checkpoint.pt"
    if not ck.exists():
        print(f"# {tree_key(tree)}: running the preview to t = {t:g} s for its state (cached in {out})", flush=True)
        subprocess.run([sys.executable, "-m", "torchsph", "cases/perpendicular_350W", "--preview", "--t-end",
                        str(t), "--quiet", "--out", str(out)] + same_model(tree), cwd=tree, env=env1(), check=True)
    return ck


def developed_checkpoint(tree: Path, t: float) -> Path:
    """The full scene run to ``t`` by the code of ``tree`` (cached)."""
    out = CACHE / tree_key(tree) / f"full_t{t:g}"
    ck = out / "checkpoint.pt"
    if not ck.exists():
        print(f"# {tree_key(tree)}: running the full scene to t = {t:g} s for its state (cached in {out})", flush=True)
        subprocess.run([sys.executable, "-m", "torchsph", "cases/perpendicular_350W", "--t-end", str(t), "--quiet",
                        "--out", str(out)] + same_model(tree), cwd=tree, env=env1(), check=True)
    return ck


def measure(tree: Path, what: str, steps: int, checkpoint: Path | None = None) -> dict:
    cmd = [sys.executable, str(DRIVER), "--tree", str(tree), what, "--steps", str(steps)]
    if checkpoint is not None:
        cmd += ["--checkpoint", str(checkpoint)]
    r = subprocess.run(cmd, env=env1(), check=True, capture_output=True, text=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


def preview_physics(key: str, t_state: float, liquidus: float = 1753.15) -> dict:
    """Per snapshot of the cached preview run: (time, highest temperature K, melt volume mm^3)
    with melt = T > T_L (volume m / rho)."""
    import h5py
    import numpy as np

    out = {}
    for f in sorted((CACHE / key / f"preview_t{t_state:g}").glob("snap_*.h5")):
        with h5py.File(f) as h:
            T, rho = np.asarray(h["temperature"]), np.asarray(h["density"])
            m = np.asarray(h["mass"]) if "mass" in h else None
            t = float(h.attrs["time"])
        melt = T > liquidus
        vol = float((m[melt] / rho[melt]).sum()) * 1e9 if m is not None else float("nan")
        out[round(t, 3)] = (t, float(T.max()), vol, int(melt.sum()))
    return out


def physics_table(ref: str, ref_key: str, t_state: float, times=(0.01, 0.02)):
    """The preview's highest temperature and melt at 10 and 20 ms, this code against ``ref``."""
    a, b = preview_physics(ref_key, t_state), preview_physics(tree_key(ROOT), t_state)
    print(f"\n| t ms | highest T {ref} K | highest T this K | difference | melt particles {ref} | melt particles this |"
          f" melt volume {ref} mm3 | melt volume this mm3 | difference |")
    print("|---|---|---|---|---|---|---|---|---|")
    for t in times:
        if round(t, 3) in a and round(t, 3) in b:
            (ta, Ta, va, na), (tb, Tb, vb, nb) = a[round(t, 3)], b[round(t, 3)]
            dv = (vb - va) / va if va else float("nan")
            print(f"| {ta * 1e3:.3f} / {tb * 1e3:.3f} | {Ta:.2f} | {Tb:.2f} | {(Tb - Ta) / Ta:+.2e} | {na} | {nb} | "
                  f"{va:.5f} | {vb:.5f} | {dv:+.2e} |")


def fmt(v, spec):
    return "-" if v is None else format(v, spec)


def split(r, kind):
    """'count: ms' of one kind of rebuild step, ``neighbour_rebuild`` or ``refresh`` (a record
    without the split: '?')."""
    n = r.get({"neighbour_rebuild": "neighbour_rebuilds", "refresh": "refreshes"}[kind])
    return "?" if n is None else f"{n}: {fmt(r[kind + '_ms'], '.0f')}"


def row(state, code, r, ref=None):
    ratio = f"{ref['ms_per_step'] / r['ms_per_step']:.2f}x" if ref else "1 (ref)"
    return (f"| {state} | {code} | {r['particles']} | {r['steps']} | {r['ms_per_step']:.1f} | "
            f"{r['ms_plain_step']:.1f} | {r['rebuilds']} | {fmt(r['rebuild_ms'], '.0f')} | "
            f"{split(r, 'neighbour_rebuild')} | {split(r, 'refresh')} | "
            f"{r['particle_steps_per_s']:.3g} | {r['peak_rss_GB']:.2f} | {fmt(r['syncs_per_plain_step'], '.0f')} | "
            f"{fmt(r['syncs_per_rebuild_step'], '.0f')} | {ratio} |")


def run(ref: str, steps: int, full_steps: int, states=("preview", "full", "developed"), t_state: float = 0.03,
        t_developed: float = 0.003, repeat: int = 3):
    head = tree_key(ROOT)
    print(f"# deposition step: this tree ({head}) against {ref}, 1 thread; "
          f"preview state at t = {t_state:g} s, {steps} steps; full scene's first {full_steps} steps; "
          f"the full scene at t = {t_developed:g} s, {full_steps} steps")
    with tempfile.TemporaryDirectory(prefix="torchsph-ref-") as tmp:
        wt = Path(tmp) / "ref"
        git("worktree", "add", "--detach", str(wt), ref)
        ref_key = tree_key(wt)
        try:
            results = {}
            for state in states:
                rounds = {"ref": [], "this": []}
                for _ in range(max(repeat, 1) if state == "preview" else 1):  # the two codes take turns
                    for name, tree in (("ref", wt), ("this", ROOT)):
                        if state == "preview":  # both codes on the reference's state; this code's own run
                            own = preview_checkpoint(tree, t_state)  # to t_state gives the physics table
                            r = measure(tree, "preview", steps, preview_checkpoint(wt, t_state) if name == "this" else own)
                        elif state == "developed":  # both codes on the reference's state
                            r = measure(tree, "preview", full_steps, developed_checkpoint(wt, t_developed))
                        else:
                            r = measure(tree, "full", full_steps)
                        rounds[name].append(r)
                        print(f"# {state} {name}: {json.dumps(r)}", flush=True)
                for name, rs in rounds.items():  # the median round (a load on the machine slows some)
                    results[state, name] = sorted(rs, key=lambda r: r["ms_per_step"])[(len(rs) - 1) // 2]
                if len(rounds["ref"]) > 1:
                    ratios = [a["ms_per_step"] / b["ms_per_step"] for a, b in zip(rounds["ref"], rounds["this"])]
                    print(f"# {state}: speed-up by round " + ", ".join(f"{q:.2f}x" for q in ratios), flush=True)
        finally:
            git("worktree", "remove", "--force", str(wt))
    if "preview" in states:
        physics_table(ref, ref_key, t_state)
    print("| state | code | particles | steps | ms/step | plain step ms | rebuilds | rebuild ms | "
          "neighbour rebuilds: ms | active-set refreshes: ms | "
          "particle-steps/s | peak RSS GB | syncs/step | syncs/rebuild step | speed-up |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for state in states:
        ref_r = results[state, "ref"]
        label = f"full, t = {t_developed * 1e3:g} ms" if state == "developed" else state
        print(row(label, ref, ref_r))
        print(row(label, head, results[state, "this"], ref_r))
    return results
