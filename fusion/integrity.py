r"""Is the covariance telling the truth? A windowed normalised-innovation test per aid.

For a consistent filter the normalised innovation squared ``ε_k = yᵀ S⁻¹ y`` of an
m-dimensional measurement is χ²(m); the sum over the last ``n`` attempts of one aid is
χ²(n·m) (Bar-Shalom, Li & Kirubarajan 2001, §5.4.2). Above its ``quantile`` the aid says
the filter's covariance is too small — the solution is then not trustworthy whatever its σ
says. Gated attempts count too: an aid rejected again and again is exactly that evidence.
Each attempt counts at most the single-attempt χ²(m) ``quantile`` (winsorised): one outlier
that the gate caught (a DVL beam on a fish: 0.5 m/s against σ 0.03) is not evidence that the
covariance lies, yet it alone pushed a 20-attempt sum over the bound and made a sound
navigation-grade solution invalid for 20 s; a covariance too small by 2× or an aid gated
again and again still fails the window.
"""
from __future__ import annotations

from collections import deque

from scipy import special


def chi2_quantile(p: float, dof: float) -> float:
    """The χ²(``dof``) quantile at probability ``p``: scipy.stats' ``chi2.ppf``, through the
    special function it calls (the same floats; scipy.stats costs the service ~20 MB of
    resident memory and ~1 s of import)."""
    return float(2.0 * special.gammaincinv(dof / 2.0, p))


class _SourceWindow:
    """One source's window: its NIS values, their sum, its dof, the window's bound, the
    single-attempt cap for that dof (one object per source: one look-up per attempt) and
    whether it is failing (in :attr:`NisMonitor._failing`: the set changed only when that does)."""

    __slots__ = ("nis", "total", "dof", "bound", "cap", "failing")

    def __init__(self, dof: int, bound: float, cap: float):
        self.nis: deque = deque()
        self.total = 0.0
        self.dof, self.bound, self.cap = dof, bound, cap
        self.failing = False


class NisMonitor:
    """Per-source sliding sums of NIS; :meth:`failing` names the sources above their bound."""

    def __init__(self, window: int, quantile: float):
        self.window = int(window)
        self.quantile = float(quantile)
        self._source: dict[str, _SourceWindow] = {}  # (an aid status at tens of Hz)
        self._bound: dict[int, float] = {}
        # the sources above their bound (full windows only): a source's verdict changes only
        # when it adds an attempt, and failing() is asked with every published state
        self._failing: set[str] = set()

    def add(self, source: str, nis: float, dof: int) -> None:
        """One attempt's NIS (finite) of a ``dof``-dimensional measurement."""
        s = self._source.get(source)
        if s is None or s.dof != dof:
            s = self._source[source] = _SourceWindow(dof, self.bound(dof), self.cap(dof))
            self._failing.discard(source)  # (a window of another dof: not failing until full)
        q = s.nis
        if s.cap < nis:  # (min(nis, cap) without the builtin's call)
            nis = s.cap
        q.append(nis)
        total = s.total + nis
        window = self.window
        n = len(q)  # (before the oldest goes: n > window is n >= window after)
        if n > window:
            total -= q.popleft()  # (the sum's same two roundings, one store)
        s.total = total
        failing = n >= window and total > s.bound
        if failing is not s.failing:  # (bools) the set only when the verdict changes
            s.failing = failing
            if failing:
                self._failing.add(source)
            else:
                self._failing.discard(source)

    def bound(self, dof: int) -> float:
        b = self._bound.get(dof)
        if b is None:
            b = self._bound[dof] = chi2_quantile(self.quantile, self.window * dof)
        return b

    def cap(self, dof: int) -> float:
        """The most one attempt counts: the single-attempt χ²(dof) ``quantile``."""
        key = -dof
        c = self._bound.get(key)
        if c is None:
            c = self._bound[key] = chi2_quantile(self.quantile, dof)
        return c

    def report(self) -> dict:
        """Per source, its window now: ``attempts`` in it, ``nis_per_dof`` — the mean NIS per
        degree of freedom (each attempt capped as :meth:`add` counts it; ≈ 1 when the covariance
        is right) — the ``bound_per_dof`` it is held to, and whether it is ``failing``."""
        out = {}
        for source, s in sorted(list(self._source.items())):
            n = len(s.nis)
            if n:
                out[source] = {"attempts": n, "nis_per_dof": s.total / (n * s.dof),
                               "bound_per_dof": s.bound / (self.window * s.dof), "failing": source in self._failing}
        return out

    def failing(self) -> list[str]:
        """Sources whose last ``window`` NIS sum exceeds the χ² bound (full windows only)."""
        return sorted(self._failing) if self._failing else []

    def clear(self, source: str | None = None) -> None:
        """Forget (after a reset: the old innovations say nothing about the new state)."""
        for s in ([source] if source is not None else list(self._source)):
            self._failing.discard(s)
            self._source.pop(s, None)
