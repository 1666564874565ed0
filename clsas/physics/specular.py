"""Specular surfaces for the simulator: planar or curved patches made of flat facets.

Each facet (centre ``p``, unit normal ``n``, in-plane axes ``u``, ``v``, sides ``a_u``, ``a_v``)
returns, in the Kirchhoff (physical-optics) approximation, for a speaker at ``T`` and a
microphone at ``R`` (unit vectors ``s_t``, ``s_r`` from ``p`` toward them, ranges ``r_t``,
``r_r``, ``q = s_t + s_r``) the echo of a point at ``p`` with the frequency response

    H(f) = reflectivity * (j f / (2 c)) * (n . q) * a_u a_v
           * sinc(f (q . u) a_u / c) * sinc(f (q . v) a_v / c) / (r_t r_r)

(``sinc(x) = sin(pi x) / (pi x)``): the facet's specular lobe, widest for small facets, and 0
where either transducer is behind the facet. Summed over facets it is the Kirchhoff integral
over the surface (exact for the linear phase across each facet; keep ``a^2 / (lambda r)``
small), so a large flat surface gives the mirror echo ``reflectivity / (2 h)`` of a
monostatic transducer at height ``h``, and a coarse scan sees its grating lobes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import validate as v

__all__ = ["Surface"]


@dataclass(frozen=True)
class Surface:
    """Flat facets that reflect specularly (see the module docstring).

    Parameters
    ----------
    centers_m : (k, 3) facet centres, m
    normals : (k, 3) or (3,) outward normals (toward the transducers)
    size_m : (k, 2) or (2,) facet sides along ``u`` and ``v``, m
    reflectivity : float
        Pressure reflection coefficient (1: rigid).
    """

    centers_m: np.ndarray
    normals: np.ndarray
    size_m: np.ndarray
    reflectivity: float = 1.0

    def __post_init__(self) -> None:
        p = v.array("centers_m", self.centers_m, shape=(None, 3))
        k = len(p)
        if k == 0:
            raise ValueError("centers_m: a surface needs at least one facet")
        n = v.unit_rows("normals", self.normals, k)
        size = np.asarray(self.size_m, float)
        size = v.array("size_m", np.broadcast_to(size, (k, 2)) if size.shape == (2,) else size, shape=(k, 2))
        if np.any(size <= 0):
            raise ValueError(f"size_m must be > 0, got min {size.min():g}")
        object.__setattr__(self, "centers_m", p)
        object.__setattr__(self, "normals", n)
        object.__setattr__(self, "size_m", size.copy())
        object.__setattr__(self, "reflectivity", v.finite("reflectivity", self.reflectivity))

    @property
    def n_facets(self) -> int:
        return len(self.centers_m)

    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        """(u, v): (k, 3) unit in-plane axes of each facet (u from x, or y where n ~ x)."""
        n = self.normals
        ref = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        u = ref - (ref * n).sum(1, keepdims=True) * n
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        return u, np.cross(n, u)

    @classmethod
    def plane(cls, center_m, extent_m, facet_m: float, normal=(0.0, 0.0, -1.0), reflectivity: float = 1.0) -> Surface:
        """A rectangle of ``extent_m`` (along the facets' u and v axes) centred at ``center_m``,
        cut into facets of side about ``facet_m``. The default normal -z faces transducers
        at smaller z looking along +z (clsas's planar rigs)."""
        c = v.array("center_m", center_m, shape=(3,))
        ext = v.array("extent_m", extent_m, shape=(2,))
        f = v.positive("facet_m", facet_m)
        nrm = v.unit_rows("normal", normal, 1)
        proto = cls(c[None], nrm, (f, f), reflectivity)
        u, w = proto.axes()
        nu, nv = (max(1, int(np.ceil(e / f))) for e in ext)
        au, av = ext[0] / nu, ext[1] / nv
        su = (np.arange(nu) - (nu - 1) / 2) * au
        sv = (np.arange(nv) - (nv - 1) / 2) * av
        gu, gv = np.meshgrid(su, sv, indexing="ij")
        pts = c + gu.reshape(-1, 1) * u[0] + gv.reshape(-1, 1) * w[0]
        return cls(pts, nrm[0], (au, av), reflectivity)

    @classmethod
    def sphere_cap(cls, apex_m, radius_m: float, extent_m, facet_m: float, reflectivity: float = 1.0) -> Surface:
        """A convex spherical cap facing -z (transducers at smaller z), apex at ``apex_m``,
        curvature radius ``radius_m``, covering ``extent_m`` in x and y: facets tangent to
        the sphere."""
        a = v.array("apex_m", apex_m, shape=(3,))
        r = v.positive("radius_m", radius_m)
        flat = cls.plane(a, extent_m, facet_m, (0.0, 0.0, -1.0), reflectivity)
        dx, dy = (flat.centers_m - a)[:, 0], (flat.centers_m - a)[:, 1]
        rho2 = dx * dx + dy * dy
        if np.any(rho2 >= r * r):
            raise ValueError("extent_m: the cap is wider than its sphere (radius_m)")
        centre = a + [0.0, 0.0, r]
        dz = r - np.sqrt(r * r - rho2)
        pts = np.c_[a[0] + dx, a[1] + dy, a[2] + dz]
        normals = pts - centre
        return cls(pts, normals, flat.size_m, reflectivity)

    def geometry(self, tx: np.ndarray, rx: np.ndarray, c_mps: float) -> dict:
        """Per (measurement, facet): ``path`` (m), ``gain`` (the frequency-flat part,
        ``reflectivity (n . q) a_u a_v / (2 c r_t r_r)``, 0 behind the facet) and ``qu``,
        ``qv`` (s: ``(q . u) a / c``, the sinc arguments per Hz)."""
        p = self.centers_m
        dt = tx[:, None, :] - p[None]
        dr = rx[:, None, :] - p[None]
        rt = np.maximum(np.linalg.norm(dt, axis=2), 1e-9)
        rr = np.maximum(np.linalg.norm(dr, axis=2), 1e-9)
        q = dt / rt[..., None] + dr / rr[..., None]
        n = self.normals[None]
        front = ((dt * n).sum(2) > 0) & ((dr * n).sum(2) > 0)
        u, w = self.axes()
        area = self.size_m[:, 0] * self.size_m[:, 1]
        gain = np.where(front, self.reflectivity * (q * n).sum(2) * area / (2 * c_mps * rt * rr), 0.0)
        return {"path": rt + rr, "gain": gain, "qu": (q * u[None]).sum(2) * self.size_m[:, 0] / c_mps,
                "qv": (q * w[None]).sum(2) * self.size_m[:, 1] / c_mps}
