"""A measured-style tabulated fabric BRDF, evaluated by a Python-registered Mitsuba BSDF.

The table has the layout of measured isotropic BRDFs (MERL-style Rusinkiewicz
half/difference angles): ``table[phi_d, theta_d, theta_h, channel]`` with
theta_h on a square-root axis (dense near the specular peak), theta_d linear
over [0, pi/2], phi_d over [0, pi) (reciprocity folds the other half). Channel 0
is the body reflectance (multiplied by the cloth texture's colour), channel 1
the white sheen. The table shipped in ``assets/fabric_brdf`` is generated from a
published fabric model: a Lambertian body plus the "Charlie" sheen
distribution (Estevez & Kulla 2017, *Production Friendly Microfacet Sheen
BRDF*) with the Neubelt & Pettineo (2013) visibility term, i.e. the cloth
model of Filament. A real measurement in the same layout can replace it.

Sampling is importance sampling of the table: with probability ``BODY_PROB`` a
cosine-weighted direction (the body), else a half vector whose theta_h follows
the table's sheen marginal (a piecewise-linear ``mi.ContinuousDistribution``)
and a uniform phi_h, reflected about it. ``pdf`` is the exact mixture density.

``register(mi)`` registers the plugin as ``clothgap_fabric`` for the current
Mitsuba variant (the class derives from that variant's ``mi.BSDF``).
"""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import numpy as np

TABLE_DIR = Path(__file__).resolve().parent.parent / "assets" / "fabric_brdf"
DEFAULT_TABLE = TABLE_DIR / "charlie-sheen.npz"
PLUGIN = "clothgap_fabric"
BODY_PROB = 0.5


def table_angles(n_h: int, n_d: int, n_phi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (theta_h, theta_d, phi_d) of the texel centres on each axis."""
    theta_h = ((np.arange(n_h) + 0.5) / n_h) ** 2 * (np.pi / 2)
    theta_d = (np.arange(n_d) + 0.5) / n_d * (np.pi / 2)
    phi_d = (np.arange(n_phi) + 0.5) / n_phi * np.pi
    return theta_h, theta_d, phi_d


def make_charlie_table(alpha: float = 0.5, n_h: int = 32, n_d: int = 32, n_phi: int = 16) -> np.ndarray:
    """Tabulate Lambert + Charlie sheen (roughness ``alpha``) as (n_phi, n_d, n_h, 2) float32."""
    theta_h, theta_d, phi_d = table_angles(n_h, n_d, n_phi)
    pd, td, th = np.meshgrid(phi_d, theta_d, theta_h, indexing="ij")  # each (n_phi, n_d, n_h)
    # Directions from the half/difference angles (phi_h = 0):
    d = np.stack([np.sin(td) * np.cos(pd), np.sin(td) * np.sin(pd), np.cos(td)], -1)
    wi = np.stack([d[..., 0] * np.cos(th) + d[..., 2] * np.sin(th), d[..., 1],
                   -d[..., 0] * np.sin(th) + d[..., 2] * np.cos(th)], -1)
    h = np.stack([np.sin(th), np.zeros_like(th), np.cos(th)], -1)
    wo = 2 * np.sum(wi * h, -1, keepdims=True) * h - wi
    ci, co = wi[..., 2], wo[..., 2]
    valid = (ci > 0) & (co > 0)
    distribution = (2 + 1 / alpha) * np.sin(th) ** (1 / alpha) / (2 * np.pi)
    visibility = 1 / (4 * np.maximum(ci + co - ci * co, 1e-4))
    body = np.where(valid, 1 / np.pi, 0.0)
    sheen = np.where(valid, distribution * visibility, 0.0)
    return np.stack([body, sheen], -1).astype(np.float32)


def save_table(path: Path, table: np.ndarray, source: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, table=table, layout="phi_d,theta_d,sqrt_theta_h,channel[body,sheen]", source=source)


def load_table(path: Path) -> np.ndarray:
    with np.load(path) as z:
        table = z["table"]
    if table.ndim != 4 or table.shape[3] != 2:
        raise ValueError(f"{path}: expected a (phi_d, theta_d, theta_h, 2) table, got shape {table.shape}")
    return table.astype(np.float32)


def sheen_marginal(table: np.ndarray, nodes: int = 64) -> np.ndarray:
    """Unnormalised density of u = sqrt(theta_h / (pi/2)) at ``nodes`` points of [0, 1], from the sheen channel."""
    n_h = table.shape[2]
    centers = (np.arange(n_h) + 0.5) / n_h
    u = np.linspace(0.0, 1.0, nodes)
    mean_sheen = np.interp(u, centers, table[..., 1].mean(axis=(0, 1)))
    theta_h = u ** 2 * np.pi / 2
    return (mean_sheen * np.sin(theta_h) * np.cos(theta_h) * np.pi * u + 1e-6).astype(np.float32)


def _half_difference_angles(dr, wi, wo):
    """The half vector ``h`` of (``wi``, ``wo``), its polar angle theta_h, and the difference angles (theta_d,
    phi_d): ``wi`` in the frame where ``h`` is the pole, phi_d folded into [0, pi)."""
    h = dr.normalize(wi + wo)
    theta_h = dr.safe_acos(h.z)
    phi_h = dr.atan2(h.y, h.x)
    # Rotate wi into the frame where h is the pole: about z by -phi_h, then about y by -theta_h.
    x = wi.x * dr.cos(phi_h) + wi.y * dr.sin(phi_h)
    y = -wi.x * dr.sin(phi_h) + wi.y * dr.cos(phi_h)
    dx = x * dr.cos(theta_h) - wi.z * dr.sin(theta_h)
    dz = x * dr.sin(theta_h) + wi.z * dr.cos(theta_h)
    theta_d = dr.safe_acos(dz)
    phi_d = dr.atan2(y, dx)
    phi_d = dr.select(phi_d < 0, phi_d + dr.pi, phi_d)
    return h, theta_h, theta_d, phi_d


def _sheen_pdf(dr, marginal, u, theta_h, wo, h, active):
    """The solid-angle density of ``wo`` under the sheen lobe: a half vector whose u = sqrt(theta_h / (pi/2)) is
    drawn from ``marginal`` and whose azimuth is uniform, ``wo`` the mirror of wi about it."""
    pdf_u = marginal.eval_pdf_normalized(u, active)
    pdf_theta_h = pdf_u / dr.maximum(dr.pi * u, 1e-6)
    pdf_h = pdf_theta_h / dr.maximum(2 * dr.pi * dr.sin(theta_h), 1e-6)
    return pdf_h / dr.maximum(4 * dr.abs(dr.dot(wo, h)), 1e-6)


def _sample_sheen(dr, mi, marginal, wi, sample2, active):
    """A direction drawn from the sheen lobe (``_sheen_pdf``'s density): ``wi`` mirrored about a drawn half vector."""
    u, _ = marginal.sample_pdf(sample2.x, active)
    theta_h = u * u * (dr.pi / 2)
    phi_h = 2 * dr.pi * sample2.y
    h = mi.Vector3f(dr.sin(theta_h) * dr.cos(phi_h), dr.sin(theta_h) * dr.sin(phi_h), dr.cos(theta_h))
    return 2 * dr.dot(wi, h) * h - wi


def _color_texture(mi: ModuleType, color):
    """``color`` as a Mitsuba texture: a texture as it is, a plain colour or number as a constant ``rgb``."""
    if isinstance(color, mi.Texture):
        return color
    return mi.load_dict({"type": "rgb", "value": np.broadcast_to(np.asarray(color, float), 3).tolist()})


def register(mi: ModuleType) -> None:
    """Register ``clothgap_fabric`` with the current Mitsuba variant."""
    import drjit as dr

    class TabulatedFabricBSDF(mi.BSDF):
        """base_color (texture) x body + sheen x sheen channel, looked up in a half/difference-angle table."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.base_color = _color_texture(mi, props["base_color"] if "base_color" in props else 0.5)
            self.sheen = float(props["sheen"]) if "sheen" in props else 1.0
            path = Path(props["filename"]) if "filename" in props else DEFAULT_TABLE
            table = load_table(path)
            self.table = mi.Texture3f(mi.TensorXf(table))
            self.marginal = mi.ContinuousDistribution([0.0, 1.0], sheen_marginal(table))
            flags = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
            self.m_components = [flags]
            self.m_flags = flags

        def _lookup(self, wi, wo):
            h, theta_h, theta_d, phi_d = _half_difference_angles(dr, wi, wo)
            u = dr.safe_sqrt(theta_h / (dr.pi / 2))
            body, sheen = self.table.eval(mi.Point3f(u, theta_d / (dr.pi / 2), phi_d / dr.pi))
            return body, sheen, h, theta_h, u

        def eval_pdf(self, ctx, si, wo, active=True):
            wi = si.wi
            active = active & (mi.Frame3f.cos_theta(wi) > 0) & (mi.Frame3f.cos_theta(wo) > 0)
            body, sheen, h, theta_h, u = self._lookup(wi, wo)
            color = self.base_color.eval(si, active)
            value = (color * body + self.sheen * sheen) * mi.Frame3f.cos_theta(wo)
            pdf_sheen = _sheen_pdf(dr, self.marginal, u, theta_h, wo, h, active)
            pdf = BODY_PROB * mi.warp.square_to_cosine_hemisphere_pdf(wo) + (1 - BODY_PROB) * pdf_sheen
            return dr.select(active, value, 0.0), dr.select(active, pdf, 0.0)

        def eval(self, ctx, si, wo, active=True):
            return self.eval_pdf(ctx, si, wo, active)[0]

        def pdf(self, ctx, si, wo, active=True):
            return self.eval_pdf(ctx, si, wo, active)[1]

        def sample(self, ctx, si, sample1, sample2, active=True):
            wo_sheen = _sample_sheen(dr, mi, self.marginal, si.wi, sample2, active)
            wo_body = mi.warp.square_to_cosine_hemisphere(sample2)
            wo = dr.select(sample1 < BODY_PROB, wo_body, wo_sheen)
            value, pdf = self.eval_pdf(ctx, si, wo, active)
            bs = mi.BSDFSample3f()
            bs.wo, bs.pdf, bs.eta = wo, pdf, 1.0
            bs.sampled_component = mi.UInt32(0)
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
            ok = active & (pdf > 0)
            return bs, dr.select(ok, value / dr.maximum(pdf, 1e-8), 0.0)

        def traverse(self, callback):
            # The colour texture is the per-clip part: exposing it lets a pooled scene take a new
            # clip's texture in place (render.scene.ScenePool); the table and sheen are per variant.
            callback.put("base_color", self.base_color, +mi.ParamFlags.Differentiable)

        def parameters_changed(self, keys=[]):
            pass

        def to_string(self):
            return f"TabulatedFabricBSDF[sheen={self.sheen}]"

    mi.register_bsdf(PLUGIN, lambda props: TabulatedFabricBSDF(props))


if __name__ == "__main__":  # python -m render.fabric_bsdf: regenerate the shipped table
    save_table(DEFAULT_TABLE, make_charlie_table(), "Lambert + Charlie sheen (Estevez & Kulla 2017), "
               "Neubelt-Pettineo visibility, alpha=0.5; render/fabric_bsdf.py make_charlie_table")
    print(f"wrote {DEFAULT_TABLE}")
