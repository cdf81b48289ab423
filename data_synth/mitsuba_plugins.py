"""The Mitsuba plugins `mitsuba_render` renders with, written in Python: `GltfBSDF`, pbrfit's
default BRDF as an ``mi.BSDF``, and `PunctualEmitter`, a point or spot light with
KHR_lights_punctual's falloff as an ``mi.Emitter``.

Their classes subclass Mitsuba's, so they are made by `plugin_classes` once mitsuba is imported
(`mitsuba_render.load_mitsuba`), once per variant.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["plugin_classes"]

#: variant -> (GltfBSDF, PunctualEmitter)
_CLASSES: dict = {}


def plugin_classes(mi, dr):
    """``(GltfBSDF, PunctualEmitter)`` of mitsuba's current variant (they subclass its types)."""
    if mi.variant() in _CLASSES:
        return _CLASSES[mi.variant()]
    from pbrfit.lighting.montecarlo import LOBE_PROB_MIN
    from pbrfit.lighting.sampling import TINY
    from pbrfit.physics.brdf import COS_MIN, MIN_ROUGHNESS, NORM2_MIN
    from pbrfit.physics.lights import MIN_DISTANCE, SPOT_MIN_COS_DELTA

    inv_pi = 1.0 / math.pi
    sided = mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide | mi.BSDFFlags.SpatiallyVarying
    glossy_flags = mi.BSDFFlags.GlossyReflection | sided
    diffuse_flags = mi.BSDFFlags.DiffuseReflection | sided

    class GltfBSDF(mi.BSDF):
        """pbrfit's default BRDF (`pbrfit.physics.brdf.evaluate_cosines`, glTF 2.0 Appendix B):

            f cos = [F D V + (1 - F) c_diff / pi] n·l,   F = f0 + (1 - f0)(1 - v·h)^5,
            f0 = mix(((ior - 1) / (ior + 1))^2, base, metallic),   c_diff = (1 - metallic) base,
            D = a^2 / (pi ((1 - (n·h)^2) + (n·h)^2 a^2)^2),   a = max(roughness, MIN_ROUGHNESS)^2,
            V = 0.5 / (n·l sqrt(a^2 + (1 - a^2)(n·v)^2) + n·v sqrt(a^2 + (1 - a^2)(n·l)^2)),

        cosines in V floored at COS_MIN, zero unless n·v > 0 and n·l > 0; ``specular=False`` drops
        F D V (and the (1 - F)), ``metallic=False`` reads metallic as 0. base color, metallic and
        roughness are read from bitmap textures at the hit's uv and clipped to [0, 1], as
        `pbrfit.render.shade.shading_inputs` does. Two-sided as pbrfit's G-buffer: where the
        incoming direction sees the back of the face (geometric normal) the shading frame is
        mirrored. Sampled as `pbrfit.lighting.montecarlo` samples it: GGX visible normals
        (Heitz 2018; Mitsuba's `MicrofacetDistribution`) or the cosine, picked by the Schlick
        weights with at least LOBE_PROB_MIN each; the density is the mixture's."""

        def __init__(self, props, base_color, metallic, roughness, model):
            mi.BSDF.__init__(self, props)
            self.base_color, self.metallic, self.roughness = base_color, metallic, roughness
            self.f0_dielectric = ((model.ior - 1.0) / (model.ior + 1.0)) ** 2
            self.specular, self.metal = bool(model.specular), bool(model.metallic)
            self.m_components = [glossy_flags, diffuse_flags]
            self.m_flags = glossy_flags | diffuse_flags

        # -- shared pieces --
        def _local(self, si):
            """(sign, wi): +1 or -1 per lane (the frame mirrored where wi sees the face's back), wi in that frame."""
            sign = dr.select(dr.dot(si.n, si.sh_frame.to_world(si.wi)) < 0.0, -1.0, 1.0)
            return sign, si.wi * sign

        def _material(self, si, active):
            base = dr.clip(self.base_color.eval(si, active), 0.0, 1.0)
            metallic = dr.clip(self.metallic.eval_1(si, active), 0.0, 1.0) if self.metal else mi.Float(0.0)
            rough = dr.clip(self.roughness.eval_1(si, active), 0.0, 1.0)
            r = dr.maximum(rough, MIN_ROUGHNESS)
            alpha = r * r
            f0 = self.f0_dielectric + (base - self.f0_dielectric) * metallic
            return base * (1.0 - metallic), f0, alpha

        def _lobes(self, ctx):
            return (self.specular and ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0),
                    ctx.is_enabled(mi.BSDFFlags.DiffuseReflection, 1))

        def _spec_prob(self, ctx, wi, c_diff, f0):
            spec, diff = self._lobes(ctx)
            if not (spec and diff):
                return mi.Float(1.0 if spec else 0.0)
            m = 1.0 - dr.clip(wi.z, 0.0, 1.0)
            ws = mi.luminance(f0 + (1.0 - f0) * (m * m * m * m * m))
            wd = mi.luminance(c_diff) * (1.0 - ws)
            return LOBE_PROB_MIN + (1.0 - 2.0 * LOBE_PROB_MIN) * ws / dr.maximum(ws + wd, TINY)

        def _value(self, ctx, wi, wo, c_diff, f0, alpha):
            """f cos at (wi, wo) in the (mirrored) shading frame."""
            spec, diff = self._lobes(ctx)
            nv, nl = wi.z, wo.z
            s = wi + wo
            s2 = dr.squared_norm(s)
            length = dr.sqrt(dr.maximum(s2, NORM2_MIN))
            vh = dr.clip(0.5 * s2 / length, 0.0, 1.0)
            m = 1.0 - vh
            fresnel = f0 + (1.0 - f0) * (m * m * m * m * m)
            out = mi.Color3f(0.0)
            if spec:
                nh = dr.clip((nv + nl) / length, 0.0, 1.0)
                sin2 = dr.clip(dr.select(s2 >= NORM2_MIN, (s.x * s.x + s.y * s.y) / dr.maximum(s2, NORM2_MIN),
                                         (1.0 - nh) * (1.0 + nh)), 0.0, 1.0)
                a2 = alpha * alpha
                b = sin2 + nh * nh * a2
                d = a2 * inv_pi / (b * b)
                nv_c = dr.clip(nv, COS_MIN, 1.0)
                nl_c = dr.clip(nl, COS_MIN, 1.0)
                root_v = dr.sqrt(a2 + (1.0 - a2) * nv_c * nv_c)
                root_l = dr.sqrt(a2 + (1.0 - a2) * nl_c * nl_c)
                v = 0.5 / (nl_c * root_v + nv_c * root_l)
                out += fresnel * (d * v)
            if diff:
                out += (1.0 - fresnel if spec else 1.0) * c_diff * inv_pi
            lit = (nv > 0.0) & (nl > 0.0)
            return dr.select(lit, out * dr.clip(nl, 0.0, 1.0), 0.0)

        def _pdf(self, ctx, wi, wo, alpha, p_spec):
            spec, diff = self._lobes(ctx)
            pdf = mi.Float(0.0)
            if spec:
                h = dr.normalize(wi + wo)
                distr = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, alpha, True)
                pdf += p_spec * distr.pdf(wi, h) / (4.0 * dr.maximum(dr.abs(dr.dot(wo, h)), TINY))
            if diff:
                pdf += (1.0 - p_spec) * mi.warp.square_to_cosine_hemisphere_pdf(wo)
            return dr.select((wi.z > 0.0) & (wo.z > 0.0), pdf, 0.0)

        # -- the interface --
        def eval(self, ctx, si, wo, active=True):
            sign, wi = self._local(si)
            c_diff, f0, alpha = self._material(si, active)
            return dr.select(active, self._value(ctx, wi, wo * sign, c_diff, f0, alpha), 0.0)

        def pdf(self, ctx, si, wo, active=True):
            sign, wi = self._local(si)
            c_diff, f0, alpha = self._material(si, active)
            return dr.select(active, self._pdf(ctx, wi, wo * sign, alpha, self._spec_prob(ctx, wi, c_diff, f0)), 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            sign, wi = self._local(si)
            c_diff, f0, alpha = self._material(si, active)
            wo_l = wo * sign
            value = self._value(ctx, wi, wo_l, c_diff, f0, alpha)
            pdf = self._pdf(ctx, wi, wo_l, alpha, self._spec_prob(ctx, wi, c_diff, f0))
            return dr.select(active, value, 0.0), dr.select(active, pdf, 0.0)

        def sample(self, ctx, si, sample1, sample2, active=True):
            sign, wi = self._local(si)
            c_diff, f0, alpha = self._material(si, active)
            spec, diff = self._lobes(ctx)
            p_spec = self._spec_prob(ctx, wi, c_diff, f0)
            pick_spec = (sample1 < p_spec) if (spec and diff) else mi.Bool(spec)
            wo = mi.warp.square_to_cosine_hemisphere(sample2)
            if spec:
                distr = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, alpha, True)
                h, _ = distr.sample(wi, sample2)
                wo = dr.select(pick_spec, mi.reflect(wi, h), wo)
            value = self._value(ctx, wi, wo, c_diff, f0, alpha)
            pdf = self._pdf(ctx, wi, wo, alpha, p_spec)
            ok = active & (wi.z > 0.0) & (pdf > 0.0)
            bs = dr.zeros(mi.BSDFSample3f)
            bs.wo = wo * sign
            bs.pdf = dr.select(ok, pdf, 0.0)
            bs.eta = mi.Float(1.0)
            bs.sampled_component = dr.select(pick_spec, mi.UInt32(0), mi.UInt32(1))
            bs.sampled_type = dr.select(pick_spec, mi.UInt32(+mi.BSDFFlags.GlossyReflection),
                                        mi.UInt32(+mi.BSDFFlags.DiffuseReflection))
            return bs, dr.select(ok, value / dr.select(ok, pdf, 1.0), 0.0)

        def to_string(self):
            return f"GltfBSDF[specular={self.specular}, metallic={self.metal}, f0_dielectric={self.f0_dielectric:.4g}]"

    class PunctualEmitter(mi.Emitter):
        """A point or spot light with KHR_lights_punctual's falloff (`pbrfit.physics.lights.incident`):
        the radiance-like value a BRDF·cos multiplies is color · intensity · window(d) · spot / d^2,
        window(d) = clamp(1 - (d / range)^4, 0, 1) for range > 0, spot = t^2 with
        t = clamp((cd - cos outer) / max(cos inner - cos outer, SPOT_MIN_COS_DELTA), 0, 1),
        cd = direction · (-l), and d floored at MIN_DISTANCE. Mitsuba's own ``spot`` falls off
        linearly in angle instead."""

        def __init__(self, props, light):
            mi.Emitter.__init__(self, props)
            self.kind = str(light.kind)
            self.position = [float(x) for x in np.asarray(light.position, np.float64)]
            self.axis = [float(x) for x in np.asarray(light.direction, np.float64)]
            self.rgb = [float(c) * float(light.intensity) for c in np.asarray(light.color, np.float64)]
            self.range = float(light.range)
            outer, inner = float(light.outer_cone_angle), float(light.inner_cone_angle)
            self.cos_outer = math.cos(outer)
            self.cos_delta = max(math.cos(inner) - math.cos(outer), SPOT_MIN_COS_DELTA)
            self.m_flags = mi.EmitterFlags.DeltaPosition

        def _value(self, to_light, dist):
            dist = dr.maximum(dist, MIN_DISTANCE)
            value = mi.Color3f(self.rgb) / dr.square(dist)
            if self.range > 0.0:
                q = dr.square(dr.square(dist / self.range))
                value *= dr.clip(1.0 - q, 0.0, 1.0)
            if self.kind == "spot":
                t = dr.clip((dr.dot(mi.Vector3f(self.axis), -to_light) - self.cos_outer) / self.cos_delta, 0.0, 1.0)
                value *= t * t
            return value

        def sample_direction(self, it, sample, active=True):
            ds = dr.zeros(mi.DirectionSample3f)
            ds.p = mi.Point3f(self.position)
            ds.pdf = mi.Float(1.0)
            ds.time = it.time
            ds.delta = mi.Bool(True)
            ds.emitter = mi.EmitterPtr(self)
            d = ds.p - it.p
            ds.dist = dr.norm(d)
            ds.d = d / ds.dist
            return ds, dr.select(active, self._value(ds.d, ds.dist), 0.0)

        def pdf_direction(self, it, ds, active=True):
            return mi.Float(0.0)

        def eval_direction(self, it, ds, active=True):
            return dr.select(active, self._value(ds.d, ds.dist), 0.0)

        def eval(self, si, active=True):
            return mi.Color3f(0.0)

        def bbox(self):
            return mi.ScalarBoundingBox3f(mi.ScalarPoint3f(self.position))

        def to_string(self):
            return f"PunctualEmitter[{self.kind}, position={self.position}]"

    _CLASSES[mi.variant()] = (GltfBSDF, PunctualEmitter)
    return GltfBSDF, PunctualEmitter
