"""When an iterative backend rebuilds its preconditioner: :class:`RebuildPolicy`.

A multigrid hierarchy (with ``mixed_amg`` also its region factors and probed Schur diagonal) built
from the tangent of one Newton state keeps preconditioning the exact matrix-free tangent of later
states, at the cost of more Krylov iterations as the tangent moves away from it. The policy is
the "ski-rental" rule counted in iterations: the first solve after a build sets the reference
rate, Krylov iterations per decade of residual reduction; every later solve adds the iterations
it needs beyond that rate's prediction to an account; once the account exceeds ``rebuild_cost``
(what a build costs, in iterations) the hierarchy is rebuilt from the next Newton iteration's
tangent, and a solve that exceeds it on its own is stopped there, the hierarchy rebuilt from its
tangent and the solve continued from the iterate it had reached (the next solve measures the new
hierarchy's rate). So the iterations lost to a stale preconditioner never exceed what a rebuild
costs.

A hierarchy that has not yet converged a solve (right after a build) gets ``give_up`` × the last
measured rate × decades + ``rebuild_cost`` iterations, those spent before a mid-solve rebuild
included; a system that needs more is far harder than the earlier ones (on the 74k leg: the state
after an overshooting first update of an activation step, where a fresh hierarchy did not
converge in 700 iterations), and the solve fails, so that Newton cuts the load increment back
instead of iterating for an hour; the next system gets a new hierarchy.

The rule counts iterations, not seconds, so that two runs of the same config take the same
decisions and give the same numbers. A backend holds one policy and tells it what happened
(:meth:`RebuildPolicy.built`, :meth:`~RebuildPolicy.new_system`, :meth:`~RebuildPolicy.account`,
:meth:`~RebuildPolicy.gave_up`); it asks :meth:`~RebuildPolicy.must_build`,
:meth:`~RebuildPolicy.budget` and :meth:`~RebuildPolicy.may_rebuild`. Its counters go into a
checkpoint (:meth:`~RebuildPolicy.counters`, :meth:`~RebuildPolicy.restore`).
"""

from __future__ import annotations

import numpy as np


class RebuildPolicy:
    """The ski-rental rebuild rule of an iterative backend's preconditioner (module docstring).

    Parameters
    ----------
    rebuild_cost : float
        What one build costs, in Krylov iterations.
    give_up : float
        A hierarchy that has not converged a solve yet gets ``give_up`` times the last measured
        rate (iterations per decade) per decade, plus ``rebuild_cost``.
    maxiter : int
        Krylov iterations per solve, at most.

    Attributes
    ----------
    rate0 : float or None
        Iterations per decade of the first solve after the last build (None: not measured yet).
    rate_last : float or None
        The last reference rate measured, of this hierarchy or an earlier one.
    excess : float
        Iterations beyond the reference rate's prediction since the last build.
    stale : bool
        Rebuild at the next Newton system.
    fresh : bool
        The hierarchy was built for the system being solved (it has no rate of its own yet there).
    """

    def __init__(self, rebuild_cost: float, give_up: float, maxiter: int):
        self.rebuild_cost = rebuild_cost
        self.give_up = give_up
        self.maxiter = maxiter
        self.rate0: float | None = None
        self.rate_last: float | None = None
        self.excess = 0.0
        self.stale = True
        self.fresh = False

    def must_build(self, have: bool) -> bool:
        """At a new Newton system: build the preconditioner (none yet, ``have`` false, or stale)?"""
        return not have or self.stale

    def new_system(self) -> None:
        """A new Newton system is prepared (the kept hierarchy is no longer fresh)."""
        self.fresh = False

    def built(self) -> None:
        """The preconditioner was (re)built from the current tangent: a new account."""
        self.rate0 = None
        self.excess = 0.0
        self.stale = False
        self.fresh = True

    def budget(self, rtol: float) -> int:
        """Iterations a solve to ``rtol`` may take: with a kept hierarchy, its reference rate's
        prediction plus what is left of the rebuild cost (then it is rebuilt); with a hierarchy
        that has not converged a solve yet, ``give_up`` times the last measured rate's prediction
        plus the rebuild cost (then the solve fails); ``maxiter`` before any rate is known."""
        decades = max(np.log10(1.0 / rtol), 1.0)
        if self.fresh or self.rate0 is None:
            if self.rate_last is None:
                return self.maxiter
            budget = self.give_up * self.rate_last * decades + self.rebuild_cost
        else:
            budget = self.rate0 * decades + self.rebuild_cost - self.excess
        return min(max(int(np.ceil(budget)), 1), self.maxiter)

    def retry_budget(self, rtol: float, spent: int) -> int:
        """Iterations left to a solve restarted after a mid-solve rebuild, ``spent`` iterations
        already done: the give-up budget counts the whole system, the stale iterations included
        (on the 74k leg an overshooting update's system would otherwise cost ~170 iterations more
        before Newton cuts the increment back)."""
        return max(min(self.budget(rtol) - spent, self.maxiter - spent), 1)

    def may_rebuild(self, status: str, spent: int) -> bool:
        """A solve stopped with ``status`` after ``spent`` iterations: rebuild and go on? (its
        budget with a kept hierarchy ran out before ``maxiter``)."""
        return status == "maxiter" and not self.fresh and spent < self.maxiter

    def gave_up(self, status: str, total: int) -> bool:
        """Did the give-up budget stop this failed solve (not ``maxiter``)? Then the hierarchy,
        built for a state Newton will now leave, is rebuilt at the next system."""
        if status == "maxiter" and total < self.maxiter:
            self.stale = True
            return True
        return False

    def account(self, its: int, rtol: float) -> None:
        """Bookkeeping after a converged solve of ``its`` iterations to ``rtol`` (not one continued
        after a mid-solve rebuild, which shows no rate of the new hierarchy)."""
        decades = max(np.log10(1.0 / rtol), 1.0)
        if self.rate0 is None:
            if its > decades:  # a solve of one iteration per decade or less (a right-hand side in a few modes) shows no rate
                self.rate0 = self.rate_last = its / decades
        elif its > 0:
            self.excess += max(its - self.rate0 * decades, 0.0)
            if self.excess > self.rebuild_cost:
                self.stale = True  # rebuilt at the next Newton system, from that state's tangent

    def counters(self) -> dict:
        """The counters a checkpoint keeps (NaN: not set)."""
        return {"rate0": np.nan if self.rate0 is None else self.rate0, "excess": self.excess,
                "stale": float(self.stale), "rate_last": np.nan if self.rate_last is None else self.rate_last}

    def restore(self, counters: dict) -> None:
        """Take the counters of :meth:`counters` back (after the hierarchy was rebuilt from the kept state)."""
        self.rate0 = None if np.isnan(counters["rate0"]) else float(counters["rate0"])
        self.excess, self.stale = float(counters["excess"]), bool(counters["stale"])
        last = counters.get("rate_last", np.nan)
        self.rate_last = None if np.isnan(last) else float(last)
