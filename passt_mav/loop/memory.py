"""What the loop remembers of where it sampled: the estimate's local error, cell by cell, from leg to leg.

Without it the planner's prior (:meth:`passt_mav.reconstruction.GPReconstructor.prior_factors`) is the
same stationary one at every leg: a cell sampled on the last leg is worth as much as one never
sampled. Where the flow holds still (the ocean default), a correction lasts several legs; where it
carries the water away (the oscillating wake), nothing is left where it was sampled. So the memory's
persistence is fitted, loop by loop, from the samples' own innovations; it is never set by hand.

Model. The prior variance of the estimate's error in cell ``c`` (component ``k``: 0 u east, 1 v
north) is ``M_kc + s_c L_kc``: ``M`` the background and offset modes' part (corrections of the whole
field, not remembered by cell), ``L`` the local part (the stationary kernels' and the state
nugget's), ``s_c`` in (0, 1] the fraction of it that past samples left. A leg's ``n_c`` samples in a
cell, with sensor variance ``sigma2``, leave the scalar Bayes fraction (each cell on its own: the
correlations between cells are left out here, the GP's posterior keeps them)::

    s_c <- s_c * (sigma2 / n_c) / (kappa * s_c * L_c + sigma2 / n_c)

and between legs the fraction relaxes back towards 1, an AR(1) error whose variance keeps a
fraction ``rho`` of a correction per leg::

    s_c <- 1 - rho * (1 - s_c)

``rho`` = 0 is the loop without memory. ``rho`` and the prior's scale ``kappa`` against the
innovations are chosen by likelihood: each leg's mean innovation per sampled cell (samples minus
the forecast at them) is Gaussian with variance ``sigma2 / n_c + kappa * (M_kc + s_c(rho) L_kc)``
under each candidate ``rho`` (its own fractions ``s(rho)``, carried alongside); the log likelihoods
add up leg by leg with a forgetting factor, as the prior weights of
:class:`passt_mav.loop.PasstLoop` do, and the most likely ``rho`` gives the fractions of the next
leg's planning prior. A tie (no cell sampled twice yet) keeps ``rho`` = 0. This is the variance
recursion of a Kalman filter with a diagonal, persistence-only transition (Jazwinski 1970,
*Stochastic Processes and Filtering Theory*, ch. 7), with its one transition parameter fitted by
the innovations' likelihood (Mehra 1970, IEEE Trans. Autom. Control 15(2), adaptive filtering).
"""

from __future__ import annotations

import numpy as np

__all__ = ["CellMemory", "RHOS"]

#: candidate persistences per leg (0 = no memory: the stationary prior every leg)
RHOS = (0.0, 0.2, 0.4, 0.6, 0.7, 0.8, 0.9)
#: candidate scales of the prior's variance against the innovations (log-spaced, 1/30 .. 30)
KAPPAS = tuple(float(k) for k in np.logspace(-1.5, 1.5, 13))


class CellMemory:
    """Per-cell fractions of the local prior variance left by past samples (see the module docstring).

    Args:
        n_cells: cells of the grid, ``R * C`` (flat index ``row * C + col``).
        forgetting: factor on the accumulated log likelihoods per leg (memory of about
            ``1 / (1 - forgetting)`` legs).
    """

    def __init__(self, n_cells: int, *, forgetting: float = 0.9, rhos=RHOS, kappas=KAPPAS):
        self.rhos = np.asarray(rhos, float)
        self.kappas = np.asarray(kappas, float)
        self.forgetting = float(forgetting)
        self.s = np.ones((self.rhos.size, int(n_cells)))  # fractions carried under each candidate rho
        self.loglik = np.zeros((self.rhos.size, self.kappas.size))
        self.best = 0  # index into rhos

    @property
    def rho(self) -> float:
        """The persistence in use (the most likely so far; 0 until a revisit says otherwise)."""
        return float(self.rhos[self.best])

    def fractions(self) -> np.ndarray:
        """(N,) fractions ``s_c`` of the local prior variance for the next leg's planning prior."""
        return self.s[self.best]

    def observe(self, cells, counts, innovation, modes_var, local_var, noise_var) -> None:
        """One leg's samples: score every ``rho``, then carry each candidate's fractions to the next leg.

        Args:
            cells: (n,) flat indices of the sampled cells (distinct).
            counts: (n,) samples in each.
            innovation: (n, 2) mean of (sample - forecast at the sample) in each cell, u and v,
                field velocity units.
            modes_var, local_var, noise_var: (2, N) the stationary prior's variance per cell from its
                modes and from its local part, and the sensor's variance, (field velocity units)^2.
        """
        cells = np.asarray(cells, int)
        if cells.size == 0:
            self.relax()
            return
        n = np.asarray(counts, float)[None, :]  # (1, n)
        d2 = np.asarray(innovation, float).T ** 2  # (2, n)
        M = np.asarray(modes_var, float)[:, cells]
        L = np.asarray(local_var, float)[:, cells]
        e = np.maximum(np.asarray(noise_var, float)[:, cells], 1e-12) / n  # (2, n)
        s = self.s[:, cells]  # (rho, n)
        # variance (rho, kappa, 2, n) of the cell-mean innovations
        v = e[None, None] + self.kappas[None, :, None, None] * (M[None, None] + s[:, None, None, :] * L[None, None])
        ll = -0.5 * np.sum(np.log(v) + d2[None, None] / v, axis=(2, 3))
        self.loglik = self.forgetting * self.loglik + ll
        # each candidate's own fractions after the leg, at its own most likely kappa
        kap = self.kappas[np.argmax(self.loglik, axis=1)]  # (rho,)
        p = kap[:, None, None] * s[:, None, :] * L[None]  # (rho, 2, n) local prior variance
        frac = np.mean(e[None] / (p + e[None]), axis=1)  # (rho, n), averaged over u and v
        self.s[:, cells] = s * frac
        best = np.unravel_index(np.argmax(self.loglik), self.loglik.shape)[0]
        # a tie keeps the lower rho (argmax takes the first): no memory until the data ask for it
        self.best = int(best)
        self.relax()

    def relax(self) -> None:
        """The step between legs: every candidate's fractions relax towards 1 by its ``rho``."""
        self.s = 1.0 - self.rhos[:, None] * (1.0 - self.s)

    def record(self) -> dict:
        """For a leg's record: the persistence in use and the mean fraction over the grid."""
        return {"rho": self.rho, "mean_fraction": float(self.fractions().mean())}
