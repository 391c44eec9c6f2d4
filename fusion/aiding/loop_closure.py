r"""Leg-to-leg loop closure: a relative position constraint between two past times (stochastic clones).

A side-scan loop closure (:class:`adaptnav.sonar.association.LoopClosure`) says that the
objects an earlier leg mapped at ``t_a`` and the new leg at ``t_b`` are the same, offset by

.. math:: δ = e(t_a) − e(t_b) + n,\qquad n ∼ N(0, R)

with ``e = p̂ − p`` the navigation's horizontal position error at each time. It constrains
the *relative* position of two epochs, so the filter keeps **clones** of its horizontal
position at past epochs (Roumeliotis & Burdick, ICRA 2002, "stochastic cloning"; Mourikis &
Roumeliotis' MSCKF): at cloning time ``d_i = p_i − p̂_i`` (error-state convention) is copied,
with its covariance ``Σ_ii = P_pp`` and its cross-covariances with the state and the older
clones. Clones are *consider* states (Schmidt): their estimates are never updated, which
keeps every update consistent while only the 18-state covariance and the cross-covariances
``C_i = Cov(δx, d_i)`` (18×2) evolve:

* propagation ``δx ← Φ δx + w``: ``C_i ← Φ C_i``;
* an ordinary update with gain ``K``: ``C_i ← (I − K H) C_i``; the reset ``G``: ``C_i ← G C_i``;
* the loop closure ``z = δ``, ``h = 0``, ``H = [−I on d_a, +I on d_b]``:
  ``S = Σ_aa + Σ_bb − Σ_ab − Σ_ba + R``, gain on the state ``K = (C_b − C_a) S⁻¹``,
  ``δx̂ = K δ``, ``P ← P − K S Kᵀ``, ``C_j ← C_j − K (Σ_bj − Σ_aj)``.

The state correction carries the drift accumulated between ``t_a`` and ``t_b`` through the
cross-covariances: position, and with it velocity, current and ``k_speed`` (the along-track
offset between legs is evidence on the speed scale).

:class:`CloneBank` holds the clones; the estimator calls its hooks (see
:mod:`adaptnav.fusion.eskf`).
"""
from __future__ import annotations

import bisect
import math

import numpy as np

from .. import kalman
from ..state import ATT, N_ERR, POS_NE


class CloneBank:
    """Horizontal-position clones of past epochs and their covariances.

    The cross-covariances are ``C_true = M C`` with ``M`` the map the kernels compose in the
    estimator's core array while clones exist (:mod:`adaptnav.fusion.kalman`, ``CORE_M``):
    every covariance step and update costs 18 × 18 there instead of 18 × 2n here (they were
    a quarter of a replay with side-scan and the calibrator); ``M`` is applied to ``C`` when
    ``C`` is read (:meth:`_settle`: a new clone, a loop closure).

    Parameters
    ----------
    period_s : float
        A new clone at most this often (:meth:`maybe_clone`).
    horizon_s : float
        Clones older than this are dropped.
    core : numpy.ndarray, optional
        The estimator's core array (``kalman.CORE_SIZE``) that carries ``M`` (a private one
        when not given).
    """

    def __init__(self, period_s: float = 5.0, horizon_s: float = 900.0, core: np.ndarray | None = None) -> None:
        self.period_s = float(period_s)
        self.horizon_s = float(horizon_s)
        self._core = np.zeros(kalman.CORE_SIZE) if core is None else core
        self._M = self._core[kalman.CORE_M].reshape(N_ERR, N_ERR)
        self.clear()

    @property
    def active(self) -> bool:
        return bool(self._ids)

    def copy(self) -> "CloneBank":
        """A copy for the estimator's snapshots (one per input sample while clones exist).

        Shares everything: the lists and ``C`` are never modified in place, only replaced
        (copy on write), Σ's rows are never modified (added per clone; a pruned one is
        harmless); ``M`` is part of the core array the snapshot copies. Copying ``C``
        (18 × 2 per clone, up to 360 columns) for every snapshot was a tenth of a replay
        with side-scan. Except the cache of relative covariances: keyed by clone ids, which a
        restored snapshot gives out again to clones of its own, the live bank's entries for
        its later clones would be read for them; the snapshot starts an empty one.
        """
        out = CloneBank.__new__(CloneBank)
        out.__dict__.update(self.__dict__)
        out._rel = {}
        return out

    def clear(self) -> None:
        self.t_s: list[float] = []
        self.pos_n_m: list[np.ndarray] = []
        # Σ between clones, a row per clone, immutable once created (shared by snapshots): id →
        # (id of its first entry, (k, 2, 2) read-only) — Σ with every clone then kept, ids
        # consecutive (made one after another, dropped oldest first), itself last — and the
        # clones' own Σ_ii in list order: :meth:`sigma`, :meth:`relative_covs` read them
        self._row_stack: dict[int, tuple[int, np.ndarray]] = {}
        self._diag = np.zeros((0, 2, 2))
        self._ids: list[int] = []
        self._rel: dict[tuple[int, int], np.ndarray] = {}  # relative_cov by clone ids
        self._next_id = 0
        self.C = np.zeros((N_ERR, 0))  # [C_0 | C_1 | ...], 2 columns per clone (times M)
        self._core[kalman.CORE_TRACK] = 0.0
        self._M[:, :] = np.eye(N_ERR)

    def _settle(self) -> None:
        """``C ← M C``, ``M ← I``: the cross-covariances as they are now."""
        if self._ids:
            self.C = self._M @ self.C
        self._M[:, :] = np.eye(N_ERR)

    # ---------------------------------------------------------------- hooks
    def transform(self, A: np.ndarray) -> None:
        """``C ← A C`` (A: Φ or the reset ``G``; 18×18)."""
        if self._ids:
            self._M[:, :] = A @ self._M

    def flush(self, core: np.ndarray, qdiag: np.ndarray) -> None:
        """Flush the pending covariance step of the estimator's core array (and ``C ← Φ C``)."""
        kalman.flush_core(core, qdiag)

    def shift_time(self, delta_s: float) -> None:
        self.t_s = [t + delta_s for t in self.t_s]

    def scale_rows(self, rows, factor: float) -> None:
        """``C[rows] ← factor · C[rows]`` (a state rescaled: ``k_speed`` at a release)."""
        if self._ids:
            self._M[rows, :] *= factor

    def zero_rows(self, rows) -> None:
        """``C[rows] ← 0``: those states were reset to values independent of every past epoch
        (the estimator's velocity and attitude resets; call it after the flush, so that the
        pending step is in ``M`` first)."""
        if self._ids:
            self._M[rows, :] = 0.0

    def maybe_clone(self, t_s: float, x_pos_n_m: np.ndarray, P: np.ndarray) -> bool:
        """Clone the horizontal position if ``period_s`` has passed since the last clone.

        ``P`` must be the covariance at ``t_s`` (flushed). Returns True when cloned.
        """
        if self.t_s and t_s - self.t_s[-1] < self.period_s:
            return False
        self._prune(t_s)
        self._settle()
        self._core[kalman.CORE_TRACK] = 1.0
        cid = self._next_id
        self._next_id += 1
        # Cov(d_new, d_old) = Cov(δx[POS_NE], d_old) = C_old[POS_NE]: the 2×2 blocks of all of
        # them copied at once, one view each (a slice and a copy per clone was a third of a clone)
        n = len(self._ids)
        stack = np.empty((n + 1, 2, 2))
        stack[:n] = self.C[POS_NE].reshape(2, n, 2).transpose(1, 0, 2)
        stack[n] = P[POS_NE, POS_NE]
        stack.setflags(write=False)
        self._row_stack[cid] = (self._ids[0] if self._ids else cid, stack)
        # new lists and arrays, not appends: snapshots share the old ones (copy())
        self._diag = np.concatenate([self._diag, stack[n:]])
        self._ids = self._ids + [cid]
        self.t_s = self.t_s + [float(t_s)]
        self.pos_n_m = self.pos_n_m + [np.asarray(x_pos_n_m, float)[:2].copy()]
        self.C = np.hstack([self.C, P[:, POS_NE]])
        return True

    def _prune(self, t_now: float) -> None:
        if not self.t_s or self.t_s[0] >= t_now - self.horizon_s:
            return  # nothing to drop (every clone but once a period)
        # clone times increase (a clone comes a period after the last): the kept ones are the
        # newest, a suffix of every list and of C's columns (C a new array, as it always is)
        k0 = bisect.bisect_left(self.t_s, t_now - self.horizon_s)
        gone = set(self._ids[:k0])
        self._ids = self._ids[k0:]
        self.t_s = self.t_s[k0:]
        self.pos_n_m = self.pos_n_m[k0:]
        self.C = self.C[:, 2 * k0:].copy()
        # the rows of dropped clones are dropped here only (snapshots never look them up
        # again); the live rows keep their entries for dropped clones (bounded, never read):
        # dropping those too rebuilt every entry per clone, 180² of them an hour in
        rows = dict(self._row_stack)  # (a new dict: snapshots share the old one)
        for cid in gone:
            rows.pop(cid, None)
        self._row_stack = rows
        self._diag = self._diag[k0:]
        self._rel = {}

    def joint_covariance(self, P: np.ndarray) -> np.ndarray:
        """The augmented covariance ``[[P, C], [Cᵀ, Σ]]`` of the error state and the clones
        ((18 + 2n) square; ``P`` the estimator's, flushed): what the clones stand for, for checks
        against a filter that carries them as states."""
        self._settle()
        n = len(self._ids)
        J = np.zeros((N_ERR + 2 * n, N_ERR + 2 * n))
        J[:N_ERR, :N_ERR] = P
        J[:N_ERR, N_ERR:] = self.C
        J[N_ERR:, :N_ERR] = self.C.T
        for i in range(n):
            for j in range(n):
                J[N_ERR + 2 * i:N_ERR + 2 * i + 2, N_ERR + 2 * j:N_ERR + 2 * j + 2] = self.sigma(i, j)
        return J

    def sigma(self, i: int, j: int) -> np.ndarray:
        """Σ between clones at list positions ``i`` and ``j`` (2×2)."""
        a, b = self._ids[i], self._ids[j]
        # stored once per pair, in the newer clone's row
        if a < b:
            first, stack = self._row_stack[b]
            return stack[a - first].T
        first, stack = self._row_stack[a]
        return stack[b - first]

    def _sigma_column(self, i: int) -> np.ndarray:
        """:meth:`sigma` ``(i, j)`` for every clone ``j`` ((n, 2, 2)): of the older ones and
        itself a slice of ``i``'s row, of each newer one its entry, transposed (two
        :meth:`sigma` calls and a difference per clone were most of a closure's :meth:`apply`)."""
        ids = self._ids
        ii = ids[i]
        first, stack = self._row_stack[ii]
        column = stack[ids[0] - first:]
        if i + 1 == len(ids):
            return column
        rows = self._row_stack
        newer = np.array([rows[ij][1][ii - rows[ij][0]] for ij in ids[i + 1:]]).transpose(0, 2, 1)
        return np.concatenate([column, newer])

    def relative_cov(self, a: int, b: int) -> np.ndarray:
        """``Σ_aa + Σ_bb − Σ_ab − Σ_ba`` (2×2, read-only): the covariance of ``d_a − d_b`` for
        clones at list positions ``a`` and ``b``. Kept per pair of clones (their Σ never
        change): a closure's update asks for it (the association's gate, for many clones at
        once, :meth:`relative_covs`)."""
        key = (self._ids[a], self._ids[b])
        out = self._rel.get(key)
        if out is None:
            out = self.sigma(a, a) + self.sigma(b, b) - self.sigma(a, b) - self.sigma(b, a)
            out.setflags(write=False)
            self._rel[key] = out
        return out

    def relative_covs(self, a: np.ndarray, b: int) -> np.ndarray:
        """:meth:`relative_cov` of every clone ``a[k]`` with clone ``b`` ((K, 2, 2)): the same
        arithmetic element by element, gathered from the rows' stacks (the association asks
        for a batch's clone against every stored sighting's, and the pruning of every new clone
        empties the per-pair cache an hour in; a loop over the distinct clones was ~0.2 ms a
        call, 400 calls per data hour). ``Σ_ab`` of an older ``a`` is in ``b``'s row, of a
        newer one in that one's row."""
        ids = self._ids
        a = np.asarray(a, dtype=np.intp).reshape(-1)
        ib = ids[b]
        first_b, row_b = self._row_stack[ib]
        ia = a + ids[0]  # (ids are consecutive)
        # Cov(d_b, d_a) for a not newer than b: b's row, as sigma() reads it (a == b: Σ_bb untransposed)
        ba = row_b[np.minimum(ia, ib) - first_b]
        s_ab, s_ba = np.where((ia == ib)[:, None, None], ba, ba.transpose(0, 2, 1)), ba
        newer = np.flatnonzero(ia > ib)
        if newer.size:  # Σ_ab stored in a's row, as (newer, older)
            ab = np.array([self._row_stack[i][1][ib - self._row_stack[i][0]] for i in ia[newer].tolist()])
            s_ab[newer], s_ba[newer] = ab, ab.transpose(0, 2, 1)
        return self._diag[a] + row_b[-1] - s_ab - s_ba

    def nearest_many(self, t_s: np.ndarray) -> np.ndarray:
        """:meth:`nearest` of every time in ``t_s`` (list positions, −1 where None)."""
        t = np.asarray(t_s, float)
        if not self.t_s:
            return np.full(t.shape, -1, dtype=np.intp)
        ts = np.array(self.t_s)
        k = np.searchsorted(ts, t, side="left")  # bisect_left
        before, after = np.maximum(k - 1, 0), np.minimum(k, ts.size - 1)
        k = np.where((k == ts.size) | ((k > 0) & (np.abs(ts[before] - t) <= np.abs(ts[after] - t))), k - 1, k)
        return np.where(np.abs(ts[k] - t) <= self.period_s, k, -1)

    def nearest(self, t_s: float) -> int | None:
        """List position of the clone nearest ``t_s`` (None if there is none within a period)."""
        ts = self.t_s
        if not ts:
            return None
        # clone times increase: the nearest is one of the two around t_s (the earlier on a
        # tie, as argmin over all of them; that array per call was 4 % of a replay)
        k = bisect.bisect_left(ts, t_s)
        if k == len(ts) or (k > 0 and abs(ts[k - 1] - t_s) <= abs(ts[k] - t_s)):
            k -= 1
        return k if abs(ts[k] - t_s) <= self.period_s else None

    # ---------------------------------------------------------------- the update
    def closure_update(self, a: int, b: int, offset_n_m, R) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Gain and innovation of a loop closure between clones ``a`` (earlier) and ``b``.

        Returns ``(K (18×2), y (2,), S (2×2), nis)``; nothing is changed (see :meth:`apply`).
        """
        self._settle()
        y = np.asarray(offset_n_m, float).reshape(2)
        S = self.relative_cov(a, b) + np.asarray(R, float).reshape(2, 2)
        S = 0.5 * (S + S.T)
        Sinv = np.linalg.inv(S)
        K = (self.C[:, 2 * b:2 * b + 2] - self.C[:, 2 * a:2 * a + 2]) @ Sinv
        nis = float(y @ Sinv @ y)
        return K, y, S, nis

    def apply(self, a: int, b: int, K: np.ndarray) -> None:
        """Cross-covariances after a fused loop closure: ``C_j ← C_j − K (Σ_bj − Σ_aj)``."""
        self._settle()
        n = len(self._ids)
        # K (Σ_bj − Σ_aj) for every clone j in one stacked product (one gemm per j, as one call
        # each did), subtracted from C's 2-column blocks (a new array: snapshots share C)
        D = self._sigma_column(b) - self._sigma_column(a)
        KD = np.matmul(K, D)  # (n, 18, 2)
        self.C = (self.C.reshape(N_ERR, n, 2) - KD.transpose(1, 0, 2)).reshape(N_ERR, 2 * n)


def reset_jacobian(dx: np.ndarray) -> np.ndarray:
    """``G`` of the ESKF reset after injecting ``dx`` (as :func:`adaptnav.fusion.kalman.inject_error`)."""
    rx, ry, rz = (float(v) for v in dx[ATT])
    G = np.eye(N_ERR)
    G[ATT, ATT] += 0.5 * np.array([[0.0, -rz, ry], [rz, 0.0, -rx], [-ry, rx, 0.0]])
    return G


def is_valid(offset_n_m, cov) -> bool:
    """A usable closure: finite offset, symmetric positive-definite covariance."""
    o = np.asarray(offset_n_m, float)
    c = np.asarray(cov, float)
    return (o.shape == (2,) and c.shape == (2, 2) and bool(np.all(np.isfinite(o)))
            and bool(np.all(np.isfinite(c))) and math.isclose(c[0, 1], c[1, 0], rel_tol=1e-6, abs_tol=1e-9)
            and bool(np.all(np.linalg.eigvalsh(0.5 * (c + c.T)) > 0)))
