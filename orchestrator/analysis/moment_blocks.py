"""A jump linear system's second moment stepped a block of steps at a time (``run_scatter``'s cost).

One step of ``run_scatter`` maps the second moment Q = E[z z^T] by Q -> M Q M^T + sum_j w_j T_j (R_j Q R_j^T)
T_j^T: M the mean map (sparse: mostly shifts), each lossy link due that step a jump of weight p (1 - p) read
through R_j (its view's rows, w x n) and carried on by T_j (n x w). Stepped one step at a time, each step
moves the whole n x n matrix two or three times: memory-bound (the study's 190-300 states over 15 566 steps,
2-7 s, most of `platoon stability-map`'s time). Over a block of L steps the same is

    Q_L = Phi Q_0 Phi^T + sum_j w_j B_j S_j B_j^T,   S_j = A_j Q_0 A_j^T + sum_(j' before j) w_j' C_jj' S_j' C_jj'^T

with Phi the block's mean map (the product of the steps' maps, still sparse), A_j = R_j Phi_(0 -> i_j) a jump's
rows read at the block's start, B_j = Phi_(i_j + 1 -> L) T_j its carry to the block's end, C_jj' =
R_j Phi_(i_j' + 1 -> i_j) T_j' what an earlier jump of the block puts where a later one reads: the same
algebra, exactly, regrouped; the full matrix is moved once a block. Pure computation (numpy, scipy).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy import sparse


class Step(Protocol):
    """One step's maps (``run_scatter._StepMaps``): the mean map and per jump (weight, T, R)."""

    mean: sparse.csr_matrix
    noises: tuple[tuple[float, np.ndarray, np.ndarray], ...]


@dataclass(frozen=True)
class Block:
    """A block of steps as one map of the second moment (module docstring)."""

    mean: sparse.csr_matrix  # Phi
    reads: np.ndarray  # the A_j stacked (rows x n)
    carries: np.ndarray  # the B_j side by side (n x rows)
    spans: tuple[tuple[int, int], ...]  # each jump's rows in reads and columns in carries
    weights: tuple[float, ...]
    couplings: tuple[tuple[int, int, np.ndarray], ...]  # (j, j', C_jj') for each j' at an earlier step than j

    def second_moment(self, q: np.ndarray) -> np.ndarray:
        """Q_L from Q_0 (symmetric)."""
        result = self.mean @ (self.mean @ q).T
        if not self.spans:
            return result
        read = self.reads @ q @ self.reads.T
        size = len(self.reads)
        injected = np.zeros((size, size))
        jumps: list[np.ndarray] = []
        for j, (start, end) in enumerate(self.spans):
            s = read[start:end, start:end].copy()
            for later, earlier, c in self.couplings:
                if later == j:
                    s += self.weights[earlier] * (c @ jumps[earlier] @ c.T)
            jumps.append(s)
            injected[start:end, start:end] = self.weights[j] * s
        return result + self.carries @ injected @ self.carries.T


def compose(steps: list[Step]) -> Block:
    """The block of ``steps``, in order (module docstring)."""
    n = steps[0].mean.shape[0]
    eye = sparse.identity(n, format="csr")
    prefix = [eye]  # Phi_(0 -> i): the block's start to step i's start
    for step in steps:
        prefix.append(sparse.csr_matrix(step.mean @ prefix[-1]))
    suffix = [eye] * len(steps)  # Phi_(i + 1 -> L): step i's end to the block's end
    after = eye
    for i in reversed(range(len(steps))):
        suffix[i] = after
        after = sparse.csr_matrix(after @ steps[i].mean)
    jumps = [(i, weight, through, rows) for i, step in enumerate(steps) for weight, through, rows in step.noises]
    spans, start = [], 0
    for _, _, _, rows in jumps:
        spans.append((start, start + len(rows)))
        start += len(rows)
    reads = (np.vstack([(prefix[i].T @ rows.T).T for i, _, _, rows in jumps]) if jumps else np.zeros((0, n)))
    carries = np.hstack([suffix[i] @ through for i, _, through, _ in jumps]) if jumps else np.zeros((n, 0))
    couplings = []
    for j, (i, _, _, rows) in enumerate(jumps):
        for e, (i_e, _, through, _) in enumerate(jumps):
            if i_e < i:
                carried = through
                for step in steps[i_e + 1:i]:
                    carried = step.mean @ carried
                couplings.append((j, e, rows @ carried))
    return Block(sparse.csr_matrix(prefix[-1]), reads, carries, tuple(spans), tuple(w for _, w, _, _ in jumps),
                 tuple(couplings))
