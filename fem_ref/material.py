"""Ogden hyperelasticity with a Prony-series viscous deviatoric stress (DESIGN.md section 2).

Strain energy (N = 1, deviatoric stretches lb_a = J^(-1/3) lambda_a):
    W = mu/alpha * (lb1^alpha + lb2^alpha + lb3^alpha - 3) + (1/d) (J - 1)^2
Viscosity follows Simo / Holzapfel: the isochoric second Piola-Kirchhoff stress S_iso feeds
one internal variable H_k per Prony term,
    H_k(n+1) = e_k H_k(n) + gamma_k (S_iso(n+1) - S_iso(n)),
    e_k = exp(-dt/tau_k),  gamma_k = g_k (1 - e_k) tau_k / dt,
and the total stress is S = S_vol + g_inf S_iso + sum_k H_k, so a held step strain relaxes the
deviatoric stress exactly as g_inf + sum_k g_k exp(-t/tau_k).

The paper's E = 12,598 Pa is not a parameter of W and is not used; the small-strain shear
modulus is mu*alpha/2 (~2.95 kPa) and the bulk modulus 2/d (~21 kPa).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import warp as wp

vec6 = wp.types.vector(length=6, dtype=wp.float32)


@dataclass(frozen=True)
class OgdenProny:
    mu: float = 364.74  # Pa
    alpha: float = 16.19
    d: float = 9.525e-5  # 1/Pa
    g: tuple[float, float] = (0.56057, 0.40585)  # Prony weights
    tau: tuple[float, float] = (6.36173, 0.73348)  # s
    density: float = 1060.0  # kg/m^3 (our choice; the paper gives none)

    @property
    def g_inf(self) -> float:
        return 1.0 - sum(self.g)

    @property
    def shear_modulus(self) -> float:
        """Small-strain shear modulus mu*alpha/2."""
        return self.mu * self.alpha / 2.0

    @property
    def bulk_modulus(self) -> float:
        return 2.0 / self.d

    def elastic(self) -> "OgdenProny":
        """The same material with viscosity switched off."""
        return OgdenProny(self.mu, self.alpha, self.d, (0.0, 0.0), self.tau, self.density)

    def wave_speed(self, stretch: float, J: float | None = None) -> float:
        """Bound of the dilatational wave speed at largest deviatoric principal stretch
        ``stretch`` and volume ratio ``J`` (default stretch^3): Ogden's tangent shear modulus
        grows like lb^alpha, the volumetric tangent is (2/d)(2J - 1). Twin of
        ``wave_speed_sq`` on the device."""
        lb = max(stretch, 1.0)
        J = lb**3 if J is None else J
        shear = self.shear_modulus * lb**self.alpha
        bulk = self.bulk_modulus * max(1.0, 2.0 * J - 1.0)
        return math.sqrt((bulk + 4.0 / 3.0 * shear) / self.density)

    def to_warp(self, dt: float) -> "MaterialParams":
        p = MaterialParams()
        p.mu, p.alpha, p.d = self.mu, self.alpha, self.d
        p.g_inf, p.density = self.g_inf, self.density
        e = [math.exp(-dt / t) for t in self.tau]
        p.e1, p.e2 = e
        p.gamma1, p.gamma2 = (gk * (1.0 - ek) * tk / dt for gk, ek, tk in zip(self.g, e, self.tau))
        return p

    @classmethod
    def from_attrs(cls, attrs: dict) -> "OgdenProny":
        """The material ``as_attrs`` wrote (a dataset's ``material`` attribute, parsed)."""
        return cls(attrs["mu"], attrs["alpha"], attrs["d"], tuple(attrs["prony_g"]), tuple(attrs["prony_tau"]),
                   attrs["density"])

    def as_attrs(self) -> dict:
        return {"mu": self.mu, "alpha": self.alpha, "d": self.d, "prony_g": list(self.g),
                "prony_tau": list(self.tau), "g_inf": self.g_inf, "density": self.density}


@wp.struct
class MaterialParams:
    mu: float
    alpha: float
    d: float
    g_inf: float
    density: float
    e1: float  # exp(-dt/tau_k)
    e2: float
    gamma1: float  # g_k (1 - e_k) tau_k / dt
    gamma2: float


@wp.func
def sym_to_vec6(m: wp.mat33):
    """Voigt order xx, yy, zz, xy, yz, xz."""
    return vec6(m[0, 0], m[1, 1], m[2, 2], m[0, 1], m[1, 2], m[0, 2])


@wp.func
def vec6_to_sym(s: vec6):
    return wp.mat33(s[0], s[3], s[5], s[3], s[1], s[4], s[5], s[4], s[2])


@wp.func
def ogden_split(F: wp.mat33, p: MaterialParams):
    """Isochoric and volumetric second Piola-Kirchhoff stress of F, with J, the largest
    deviatoric principal stretch and the strain energy density W(F) [J/m^3] (a few flops from
    the same powers; dropped by the compiler where unused). From C = F^T F = V diag(s^2) V^T
    (a symmetric eigenproblem, cheaper than the SVD of F and all that is needed), principal
    Kirchhoff stresses tau_a map to S = V diag(tau_a / s_a^2) V^T."""
    V = wp.mat33()
    s2 = wp.vec3()
    wp.eig3(wp.transpose(F) * F, V, s2)
    J = wp.determinant(F)
    jm23 = wp.pow(wp.abs(J), -2.0 / 3.0)
    h = 0.5 * p.alpha
    p0 = wp.pow(jm23 * s2[0], h)
    p1 = wp.pow(jm23 * s2[1], h)
    p2 = wp.pow(jm23 * s2[2], h)
    mean = (p0 + p1 + p2) / 3.0
    kirchhoff_vol = J * (2.0 / p.d) * (J - 1.0)  # J * dU/dJ
    inv2 = wp.vec3(1.0 / s2[0], 1.0 / s2[1], 1.0 / s2[2])
    d_iso = wp.vec3(p.mu * (p0 - mean) * inv2[0], p.mu * (p1 - mean) * inv2[1], p.mu * (p2 - mean) * inv2[2])
    Vt = wp.transpose(V)
    S_iso = V * wp.diag(d_iso) * Vt
    S_vol = V * wp.diag(kirchhoff_vol * inv2) * Vt
    W = p.mu / p.alpha * (p0 + p1 + p2 - 3.0) + (J - 1.0) * (J - 1.0) / p.d
    return S_iso, S_vol, J, wp.sqrt(jm23 * wp.max(s2)), W


@wp.func
def wave_speed_sq(p: MaterialParams, lb: float, J: float):
    """Squared wave speed bound at deviatoric stretch lb and volume ratio J (see
    OgdenProny.wave_speed)."""
    shear = 0.5 * p.mu * p.alpha * wp.pow(wp.max(lb, 1.0), p.alpha)
    bulk = (2.0 / p.d) * wp.max(1.0, 2.0 * J - 1.0)
    return (bulk + 4.0 / 3.0 * shear) / p.density
