"""Limited-memory BFGS inverse-Hessian approximation (two-loop recursion).

The initial inverse Hessian is ``gamma M^{-1}`` with an optional SPD operator M (the inner
product of the parameter space, e.g. an H1 or elasticity Riesz map of a shape control) and the
usual scaling ``gamma = s.y / (y.M^{-1}y)`` of the newest pair (Nocedal & Wright, eq. 7.20).
"""

from collections.abc import Callable

import numpy as np

__all__ = ["LBFGSMemory"]


class LBFGSMemory:
    """The last ``size`` pairs s = q_{k+1} - q_k, y = g_{k+1} - g_k.

    Args:
        size: Number of pairs kept.
        inner_product: ``g -> M^{-1} g`` for an SPD operator M (default identity).
        curvature_tol: Pairs with ``s.y <= curvature_tol max(|s| |y|, |g.s|)`` are skipped,
            keeping the approximation positive definite (and its scale meaningful) without a
            Wolfe curvature condition.
    """

    def __init__(
        self,
        size: int,
        inner_product: Callable[[np.ndarray], np.ndarray] | None = None,
        curvature_tol: float = 1e-10,
    ) -> None:
        self.size = size
        self.inner_product = inner_product
        self.curvature_tol = curvature_tol
        self.s: list[np.ndarray] = []
        self.y: list[np.ndarray] = []
        self.gamma: float | None = None

    def __len__(self) -> int:
        return len(self.s)

    @property
    def scaled(self) -> bool:
        """Whether the approximation knows the scale of the problem (a pair was ever kept)."""
        return self.gamma is not None

    def reset(self, keep_scaling: bool = False) -> None:
        """Forget all pairs; the next direction is ``-gamma M^{-1} g``.

        Args:
            keep_scaling: Keep gamma of the newest pair (else gamma = 1 and the problem's scale
                is unknown again).
        """
        self.s.clear()
        self.y.clear()
        if not keep_scaling:
            self.gamma = None

    def update(self, s: np.ndarray, y: np.ndarray, decrease: float = 0.0) -> bool:
        """Add a pair if it has positive curvature; returns whether it was added.

        Args:
            s: Step q_{k+1} - q_k.
            y: Gradient change g_{k+1} - g_k.
            decrease: ``|g_k . s|``, the first-order change along the step; a curvature
                ``s.y`` below ``curvature_tol`` times it is round-off (e.g. of a linear
                objective) and is skipped, as in L-BFGS-B.
        """
        if self.size == 0:
            return False
        sy = float(s @ y)
        threshold = max(np.linalg.norm(s) * np.linalg.norm(y), abs(decrease))
        if not sy > self.curvature_tol * threshold:
            return False
        self.s.append(np.array(s, dtype=float))
        self.y.append(np.array(y, dtype=float))
        if len(self.s) > self.size:
            del self.s[0], self.y[0]
        self.gamma = sy / float(y @ self._initial(y))
        return True

    def _initial(self, r: np.ndarray) -> np.ndarray:
        return np.asarray(self.inner_product(r), dtype=float) if self.inner_product else r.copy()

    def apply(self, g: np.ndarray, free: np.ndarray | None = None) -> np.ndarray:
        """``H_F g_F``: the inverse-Hessian approximation of the free variables applied to g.

        With a mask ``free`` the pairs are restricted to the free variables (pairs without
        positive curvature there are skipped) and the result vanishes on the others, so
        ``-apply(g, free)`` is a descent direction of the bound-constrained problem. The
        restriction is the reduced inverse Hessian for pairs whose steps kept the fixed
        variables fixed (the optimiser resets the memory when the active set changes).
        """
        mask = np.ones(g.shape, dtype=bool) if free is None else np.asarray(free, dtype=bool)
        r = np.where(mask, g, 0.0)
        pairs = []
        for s, y in zip(self.s, self.y, strict=True):
            s, y = np.where(mask, s, 0.0), np.where(mask, y, 0.0)
            sy = float(s @ y)
            if sy > self.curvature_tol * np.linalg.norm(s) * np.linalg.norm(y):
                pairs.append((s, y, 1.0 / sy))
        alphas = []
        for s, y, rho in reversed(pairs):
            a = rho * float(s @ r)
            r -= a * y
            alphas.append(a)
        r = np.where(mask, self._initial(r), 0.0)
        if pairs:
            s, y, rho = pairs[-1]
            r *= 1.0 / (rho * float(y @ np.where(mask, self._initial(y), 0.0)))
        elif self.gamma is not None:
            r *= self.gamma
        for (s, y, rho), a in zip(pairs, reversed(alphas), strict=True):
            b = rho * float(y @ r)
            r += (a - b) * s
        return np.where(mask, r, 0.0)

    def state(self) -> dict[str, np.ndarray]:
        """Arrays that restore the memory with :meth:`load`."""
        n = len(self.s[0]) if self.s else 0
        return {
            "s": np.array(self.s).reshape(len(self.s), n),
            "y": np.array(self.y).reshape(len(self.y), n),
            "gamma": np.array(np.nan if self.gamma is None else self.gamma),
        }

    def load(self, state: dict[str, np.ndarray]) -> None:
        """Restore pairs saved by :meth:`state`."""
        self.s = [np.array(row) for row in state["s"]]
        self.y = [np.array(row) for row in state["y"]]
        gamma = float(state["gamma"])
        self.gamma = None if np.isnan(gamma) else gamma
