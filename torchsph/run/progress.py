"""What a run costs, said before and while it runs: the cost estimate and the progress bar.

The bar counts process time (or steps, for ``--steps``); a restarted run continues it
from the checkpoint's time. Its ETA is the remaining process time divided by the rate
over a moving window of wall time (process seconds per wall second over the last
``window_s``), not over the whole run and not from the last update: a run whose step
shrinks as the melt appears shows the new rate within one window, and does not swing
with each rebuild. Throughput is given for the particles integrated (the active set)
and for all particles, labelled.
"""
from __future__ import annotations

import collections
import math
import time

GB = 1024.0**3


def hms(seconds: float) -> str:
    """'3 h 05 min', '12 min 30 s', '45 s'; '?' if unknown."""
    if seconds is None or not math.isfinite(seconds) or seconds < 0:
        return "?"
    s = int(round(seconds))
    if s >= 86400 * 2:
        return f"{s / 86400:.1f} days"
    if s >= 3600:
        return f"{s // 3600} h {(s % 3600) // 60:02d} min"
    if s >= 60:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s} s"


class MovingRate:
    """Rates of several counters per wall second over the last ``window_s`` of wall time."""

    def __init__(self, window_s: float = 120.0):
        self.window_s = window_s
        self.samples: collections.deque = collections.deque()

    def add(self, wall: float, *counters: float):
        self.samples.append((wall, *counters))
        while len(self.samples) > 2 and wall - self.samples[1][0] >= self.window_s:
            self.samples.popleft()

    def rates(self) -> list[float] | None:
        if len(self.samples) < 2:
            return None
        a, b = self.samples[0], self.samples[-1]
        dw = b[0] - a[0]
        if dw <= 0:
            return None
        return [(y - x) / dw for x, y in zip(a[1:], b[1:])]


class Progress:
    """One bar for a run (rank 0 of an MPI run; disabled elsewhere or with ``--quiet``).

    ``total``/``start``: the end and the start of the run in the bar's unit (process
    seconds, or steps). :meth:`update` takes the current position, the step's dt and
    binding limit, and the particle counts (all, integrated) summed over ranks."""

    def __init__(self, total: float, start: float, by_steps: bool, enabled: bool, window_s: float = 120.0):
        from tqdm import tqdm

        self.total, self.start, self.by_steps = total, start, by_steps
        self.rate = MovingRate(window_s)
        self.t0 = time.perf_counter()
        self.psteps_all = self.psteps_active = 0.0
        unit = "step" if by_steps else "s"
        self.bar = tqdm(total=total, initial=start, disable=not enabled, unit=unit, dynamic_ncols=True,
                        mininterval=0.5, bar_format="{l_bar}{bar}| {n:.4g}/{total:.4g} " + unit
                        + " [{elapsed}{postfix}]")
        self.pos = start
        self.rate.add(self.t0, start, 0.0, 0.0)

    def update(self, pos: float, n_all: int, n_active: int, text: str = "", refresh_text: bool = True):
        """Advance to ``pos``; ``text`` (step, t, dt, limit) is shown with the ETA."""
        self.psteps_all += n_all
        self.psteps_active += n_active
        self.bar.update(pos - self.pos)
        self.pos = pos
        if refresh_text:
            now = time.perf_counter()
            self.rate.add(now, pos, self.psteps_active, self.psteps_all)
            self.bar.set_postfix_str(self.postfix(text), refresh=False)

    def eta(self) -> float | None:
        r = self.rate.rates()
        if r is None or r[0] <= 0:
            return None
        return (self.total - self.pos) / r[0]

    def postfix(self, text: str) -> str:
        r = self.rate.rates()
        if r is None:
            return text
        return (f"{text} | {r[1]:.3g} active p-steps/s ({r[2]:.3g} all) | ETA {hms(self.eta())}").strip(" |")

    def close(self):
        self.bar.close()


def projection_lines(n_all: int, n_active: int, rss_gb: float | None, ranks: int, steps_left: float,
                     dt_s: float, dt_why: str, snapshots: int, snapshot_bytes: float,
                     probe: tuple[int, float] | None, threads: str | None = None,
                     disk_free: float | None = None) -> list[str]:
    """The cost block printed before a run (and by ``--estimate``). ``probe``: (steps, wall
    seconds) of a short probe, or None before it; ``threads``: how many CPU threads, and why;
    ``disk_free``: bytes free where the run writes (None: not known)."""
    need = snapshots * snapshot_bytes
    out = [f"cost: {n_all:,} particles ({n_active:,} integrated now) on {ranks} process"
           + ("es" if ranks > 1 else "") + (f", {threads}" if threads else "")
           + (f"; memory {rss_gb:.2f} GB peak so far per process" if rss_gb is not None else ""),
           f"cost: ~{steps_left:,.0f} steps to the end at dt ~ {dt_s:.3g} s ({dt_why}); "
           f"{snapshots} snapshots, ~{need / GB:.2f} GB on disk"
           + (f" ({disk_free / GB:.2f} GB free there)" if disk_free is not None else "")]
    if probe is None and disk_free is not None and need > disk_free:  # (said once, before the probe)
        out.append("cost: the snapshots need more than the free disk: the run will stop when it fills (its last "
                   "checkpoint kept); make room, or write fewer: --set run.output_interval_s=...")
    if probe is not None:
        k, wall = probe
        per = wall / max(k, 1)
        total = per * steps_left
        low = []  # why the probe's steps cost less than the run's will
        if "once melt flows" in dt_why:
            low.append("the probe ran before the melt, and a step with melt costs more: 5x on the deposition "
                       "preview")
        if 0 < n_active < 0.5 * n_all:
            low.append(f"where heat spreads {n_all / n_active:.0f}x as many particles may come to work")
        out.append(f"cost: probe {k} steps in {wall:.2f} s ({1e3 * per:.1f} ms/step): projected wall time "
                   f"{hms(total)} on this machine at today's work per step"
                   + (f" (a lower bound: {'; '.join(low)})" if low else ""))
        if total > 3600:
            out.append("cost: over an hour. Cheaper: --preview (the case's coarse variant), more ranks "
                       "(mpirun -n K), --device cuda, a coarser --set scene.dx_m=..., or --t-end / --steps "
                       "for a shorter window; the work per step grows as the heated zone grows")
    return out
