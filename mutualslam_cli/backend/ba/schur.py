"""Sparse normal equations of the photometric BA and their Schur complement.

The Gauss–Newton system has a camera block ``H_cc`` (:data:`~mutualslam_cli.backend.ba.problem.NP`
unknowns per keyframe), a diagonal inverse-depth block ``H_pp`` and the coupling ``H_cp``.
The points are eliminated with the Schur complement on the diagonal inverse-depth block
(Triggs et al. 2000, "Bundle adjustment — a modern synthesis", §6); the reduced camera system
(8 unknowns per free keyframe) is solved densely. :class:`BlockStructure` holds the static
sparsity and assembles the blocks; :class:`NormalEquations` takes one damped LM step from them.
"""

from __future__ import annotations

import numpy as np

from mutualslam_cli.backend.ba.problem import NP


class BlockStructure:
    """Static sparsity of the normal equations. Observations are sorted by (host, target)
    keyframe pair, so each pair's 8×8 blocks come from one contiguous run of residuals."""

    def __init__(self, host: np.ndarray, p: np.ndarray, t: np.ndarray, nk: int):
        h = host[p]
        self.nk, self.host, self.p, self.h, self.t = nk, host, p, h, t
        key = h * nk + t
        self.starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]]) if len(key) else key[:0]
        self.ends = np.r_[self.starts[1:], len(key)]
        self.ph, self.pt = h[self.starts], t[self.starts]

    def scatter_vec(self, kf: np.ndarray, V: np.ndarray) -> np.ndarray:
        """Sum rows of ``V`` ``(N, 8)`` into the ``(8K,)`` vector at keyframes ``kf``."""
        idx = (kf[:, None] * NP + np.arange(NP)).ravel()
        return np.bincount(idx, V.ravel(), minlength=self.nk * NP)

    def camera_system(self, Jc: np.ndarray, Jw: np.ndarray, bblk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Dense ``H_cc`` ``(8K, 8K)`` and ``b_c`` ``(8K,)``: every residual of one (host,
        target) pair adds to the same 16×16 block, so each pair is one small matrix product
        (a loop over keyframe pairs, not over points)."""
        nk, S = self.nk, Jc.shape[1]
        J2, W2 = Jc.reshape(-1, 2 * NP), Jw.reshape(-1, 2 * NP)
        B = np.empty((len(self.starts), 2 * NP, 2 * NP))
        for u, (a, b) in enumerate(zip(self.starts * S, self.ends * S)):
            B[u] = W2[a:b].T @ J2[a:b]
        kf = np.r_[self.ph, self.pt]
        Dv = np.concatenate([B[:, :NP, :NP], B[:, NP:, NP:]]).reshape(len(kf), -1)
        D = np.bincount((kf[:, None] * NP * NP + np.arange(NP * NP)).ravel(), Dv.ravel(),
                        minlength=nk * NP * NP).reshape(nk, NP, NP)
        H: np.ndarray = np.zeros((nk, NP, nk, NP))  # (K, 8, K, 8), then (8K, 8K)
        H[self.ph, :, self.pt, :] = B[:, :NP, NP:]  # (h, t) cross blocks, unique per pair
        H = H.reshape(nk * NP, nk * NP)
        H = H + H.T
        H4 = H.reshape(nk, NP, nk, NP)
        H4[np.arange(nk), :, np.arange(nk), :] += D
        b = self.scatter_vec(np.r_[self.h, self.t], np.concatenate([bblk[:, :NP], bblk[:, NP:]]))
        return H, b

    def _chunks(self) -> list:
        """Points grouped by host keyframe, with the keyframes their observations touch."""
        out, P = [], len(self.host)
        ps = np.argsort(self.host, kind="stable")
        pb = np.searchsorted(self.host[ps], np.arange(self.nk + 1))
        ob = np.searchsorted(self.h, np.arange(self.nk + 1))  # observations sorted by host
        for k in range(self.nk):
            pts, obs = ps[pb[k]:pb[k + 1]], np.arange(ob[k], ob[k + 1])
            if len(pts) == 0:
                continue
            touched = np.unique(np.r_[k, self.t[obs]])
            out.append((pts, obs, touched, int(np.searchsorted(touched, k)),
                        np.searchsorted(touched, self.t[obs]), np.searchsorted(pts, self.p[obs])))
        assert sum(len(c[0]) for c in out) == P
        return out

    def schur(self, A: np.ndarray, Ct: np.ndarray, inv_hd: np.ndarray, frow: np.ndarray) -> np.ndarray:
        """``H_cp H_pp⁻¹ H_pc`` on the free keyframes ``(8F, 8F)``.

        Each point's column of ``H_cp`` has at most ``1 + max_targets`` non-zero 8-blocks (host
        slot ``A`` ``(P, 8)``, target slots ``Ct`` ``(M, 8)``). Per host keyframe, the columns
        scaled by ``H_pp^{-1/2}`` form a dense ``Z`` over the few keyframes they touch and
        ``Z Zᵀ`` is added to those rows/columns (a loop over keyframes, BLAS inside).
        ``frow`` ``(K,)`` maps a keyframe to its free index, ``F`` if fixed.
        """
        if not hasattr(self, "chunks"):
            self.chunks = self._chunks()
        F = int(frow.max(initial=0))
        sq = np.sqrt(inv_hd)
        S = np.zeros((F * NP, F * NP))
        for pts, obs, touched, lh, lt, lc in self.chunks:
            Z = np.zeros((len(touched), NP, len(pts)))
            Z[lh] = (A[pts] * sq[pts][:, None]).T
            Z[lt, :, lc] = Ct[obs] * sq[self.p[obs]][:, None]
            fr = frow[touched]
            keep = fr < F
            Zf = Z[keep].reshape(-1, len(pts))
            rows = (fr[keep][:, None] * NP + np.arange(NP)).ravel()
            S[np.ix_(rows, rows)] += Zf @ Zf.T
        return S


class NormalEquations:
    """Gauss–Newton normal equations in Schur form (point block diagonal)."""

    def __init__(self, structure: BlockStructure, Hcc: np.ndarray, bc: np.ndarray, A: np.ndarray, Ct: np.ndarray,
                 Hpp: np.ndarray, bp: np.ndarray) -> None:
        self.structure, self.Hcc, self.bc, self.A, self.Ct, self.Hpp, self.bp = structure, Hcc, bc, A, Ct, Hpp, bp

    def step(self, lam: float, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """LM step ``(dc (8K,), dp (P,))`` with damping ``λ·diag(H)``; ``cols`` are the
        optimised columns of ``dc`` (sorted, keyframe-major)."""
        structure, A, Ct = self.structure, self.A, self.Ct
        fk = np.unique(cols // NP)
        frow = np.full(structure.nk, len(fk))
        frow[fk] = np.arange(len(fk))
        loc = frow[cols // NP] * NP + cols % NP  # column positions inside the free block
        Hd = self.Hpp * (1 + lam) + 1e-12
        Ssch = structure.schur(A, Ct, 1.0 / Hd, frow)[np.ix_(loc, loc)]
        Sf = self.Hcc[np.ix_(cols, cols)] - Ssch  # reduced camera system (Schur complement)
        q = self.bp / Hd
        g = self.bc - structure.scatter_vec(np.r_[structure.host, structure.t],
                                            np.concatenate([A * q[:, None], Ct * q[structure.p][:, None]]))
        hdiag = np.diag(self.Hcc)[cols]
        Sf[np.diag_indices_from(Sf)] += lam * np.maximum(hdiag, 1e-6) + 1e-9
        dc = np.zeros(len(self.bc))
        dc[cols] = -np.linalg.solve(Sf, g[cols])
        dck = dc.reshape(-1, NP)
        Hcp_dc = np.einsum("pi,pi->p", A, dck[structure.host]) + np.bincount(
            structure.p, np.einsum("mi,mi->m", Ct, dck[structure.t]), minlength=len(Hd))
        return dc, -(self.bp + Hcp_dc) / Hd  # back-substitution
