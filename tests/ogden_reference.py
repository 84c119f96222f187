"""Independent float64 references for the FEM tests (numpy only, no Warp, no project code).

The Cauchy stress is obtained by central finite differences of the strain energy W(F), so the
solver's principal-stress formula is checked against the definition P = dW/dF.
"""

import numpy as np

MU, ALPHA, D = 364.74, 16.19, 9.525e-5
G = (0.56057, 0.40585)
TAU = (6.36173, 0.73348)


def energy(F):
    J = np.linalg.det(F)
    lam2 = np.linalg.eigvalsh(F.T @ F)  # squared principal stretches
    lb = J ** (-1.0 / 3.0) * np.sqrt(lam2)
    return MU / ALPHA * (np.sum(lb**ALPHA) - 3.0) + (J - 1.0) ** 2 / D


def cauchy_fd(F, h=1e-6):
    """sigma = (1/J) P F^T with P_ij = dW/dF_ij by central differences."""
    P = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            E = np.zeros((3, 3))
            E[i, j] = h
            P[i, j] = (energy(F + E) - energy(F - E)) / (2 * h)
    return P @ F.T / np.linalg.det(F)


def cauchy_principal(stretches):
    """Closed-form Ogden Cauchy stresses for a diagonal F = diag(stretches)."""
    lam = np.asarray(stretches, float)
    J = lam.prod()
    p = (J ** (-1 / 3) * lam) ** ALPHA
    return MU * (p - p.mean()) / J + 2.0 / D * (J - 1.0)


def voigt(s):
    """xx, yy, zz, xy, yz, xz."""
    return np.array([s[0, 0], s[1, 1], s[2, 2], s[0, 1], s[1, 2], s[0, 2]])


def relaxation(t):
    """Normalised deviatoric relaxation function g_inf + sum g_k exp(-t/tau_k)."""
    t = np.asarray(t, float)
    return 1.0 - sum(G) + sum(g * np.exp(-t / tau) for g, tau in zip(G, TAU))
