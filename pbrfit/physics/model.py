"""`Model`: which BRDF terms, lobes and light paths are on.

A `Model` is a frozen, hashable dataclass. It is passed to jitted functions as a static
argument, so a term that is off is never traced, let alone computed. The default is the
glTF 2.0 metallic-roughness BRDF (glTF 2.0 specification, Appendix B).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from typing import Optional

__all__ = ["Model", "DISTRIBUTIONS", "GEOMETRIES", "FRESNELS", "DIFFUSES", "IBLS"]

#: Normal distribution functions: GGX / Trowbridge-Reitz (glTF, Filament) and Beckmann.
DISTRIBUTIONS = ("ggx", "beckmann")
#: Masking-shadowing variants.
#:  - ``smith_ggx_correlated``: height-correlated Smith for GGX (Heitz 2014), glTF and Filament's V.
#:  - ``smith_ggx_separable``: uncorrelated product G1(v) G1(l) with the exact GGX G1 (Walter 2007).
#:  - ``schlick_ggx_direct``: Schlick-GGX product with k = (r + 1)^2 / 8 (Karis 2013, punctual).
#:  - ``schlick_ggx_ibl``: Schlick-GGX product with k = alpha / 2 (Karis 2013, image-based).
#:  - ``smith_beckmann_correlated``: height-correlated Smith with Beckmann's Λ (Walter 2007,
#:    Heitz 2014): the masking that belongs with ``distribution="beckmann"`` (the GGX terms
#:    paired with Beckmann's D lose energy: the weak white furnace gives 0.79 at alpha 0.3; this
#:    term paired with GGX's D, the default distribution, creates it: the specular albedo with
#:    F = 1 is 1.25 at roughness 0.3 and 1.54 at 0.7, at n·v = 0.05). Mixed pairs are accepted
#:    for studies of the mismatch; a fit should pair each D with its own masking.
GEOMETRIES = ("smith_ggx_correlated", "smith_ggx_separable", "schlick_ggx_direct", "schlick_ggx_ibl",
              "smith_beckmann_correlated")
#: Fresnel variants: Schlick's approximation for both lobes, or the exact unpolarised dielectric
#: Fresnel equation (at ``ior``) for the dielectric lobe with Schlick for the metal lobe.
FRESNELS = ("schlick", "dielectric")
#: Diffuse lobes: Lambert (glTF), Burley (Disney 2012), or none.
DIFFUSES = ("lambert", "burley", "none")
#: Environment-light integrators: split sum (Karis 2013); per-pixel lobe integrals tabulated over
#: roughness for fixed geometry (`pbrfit.lighting.pixel_ibl`, the fit's exact option); Monte Carlo (the
#: reference integrator, `pbrfit.lighting.montecarlo`); or none.
IBLS = (None, "split_sum", "per_pixel", "monte_carlo")


@dataclasses.dataclass(frozen=True)
class Model:
    """Static configuration of the reflectance model.

    Attributes:
        distribution: normal distribution function, one of `DISTRIBUTIONS`.
        geometry: masking-shadowing term, one of `GEOMETRIES`.
        fresnel: Fresnel term, one of `FRESNELS`.
        diffuse: diffuse lobe, one of `DIFFUSES`.
        specular: whether the specular (microfacet) lobe is on.
        metallic: whether the metal lobe is on; when off, metallic is treated as 0 everywhere
            (the scene has no metal) and the metal mix is not computed.
        multiscatter: multiple-scattering energy compensation (Kulla & Conty 2017, in
            Filament's ``1 + f0 (1 / (scale + bias) - 1)`` form) on the specular lobe.
        ibl: how environment light is integrated, one of `IBLS`; ``None`` means the scene has
            no environment and no image-based-lighting code runs.
        ior: index of refraction of the dielectric lobe (1.5 gives glTF's F0 = 0.04).
    """

    distribution: str = "ggx"
    geometry: str = "smith_ggx_correlated"
    fresnel: str = "schlick"
    diffuse: str = "lambert"
    specular: bool = True
    metallic: bool = True
    multiscatter: bool = False
    ibl: Optional[str] = None
    ior: float = 1.5

    def __post_init__(self):
        _check("distribution", self.distribution, DISTRIBUTIONS)
        _check("geometry", self.geometry, GEOMETRIES)
        _check("fresnel", self.fresnel, FRESNELS)
        _check("diffuse", self.diffuse, DIFFUSES)
        _check("ibl", self.ibl, IBLS)
        for name in ("specular", "metallic", "multiscatter"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"Model.{name} must be True or False, got {getattr(self, name)!r}")
        if isinstance(self.ior, bool) or not isinstance(self.ior, numbers.Real) \
                or not (math.isfinite(self.ior) and self.ior >= 1.0):
            raise ValueError(f"Model.ior must be a finite number >= 1, got {self.ior!r}")
        object.__setattr__(self, "ior", float(self.ior))  # numpy scalars too: a plain, hashable float

    def replace(self, **changes) -> "Model":
        """A copy with some fields changed (validated like the constructor)."""
        return dataclasses.replace(self, **changes)

    def describe(self) -> dict:
        """The fields as a plain dict (for reports)."""
        return dataclasses.asdict(self)


def _check(field: str, value, allowed) -> None:
    if value not in allowed:
        names = ", ".join(repr(a) for a in allowed)
        raise ValueError(f"unknown Model.{field} {value!r}; expected one of {names}")
