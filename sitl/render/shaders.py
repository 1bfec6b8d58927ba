"""GLSL 3.30 sources of the renderer's passes, shaped by what Mesa llvmpipe is fast and slow at.

This module holds the sensor model the passes share, the post pass and the mask pass; the scene pass's
shaders (materials, sky, and the bakes of the ground texture and the sky) are
:mod:`sitl.render.scene_shaders`.

Measured on the 2-core CI machine at 640x480: a full-screen pass costs ~1 ms; one ``texelFetch`` from
an RGBA8 texture ~0.4 ms but ~1.5 ms from a float texture and ~5 ms for a filtered ``texture()``;
``pow`` costs as much as a fetch; a loop with a uniform bound costs ~6 ms even when it runs zero times,
and both sides of a branch run. Hence: every texture is RGBA8 read with ``texelFetch`` (mip levels picked
by hand from screen-space derivatives); one program per material group instead of a branch chain;
post-pass variants compiled with ``#define`` and loops with constant bounds; depth travels as
disparity (``f B / Z``, px) in 24 bits of RGBA8 so that decoding it is one dot product.

Passes:
    1. scene: the world by material group (ground, generic, foliage), distractors, the leader, the sky
       where nothing was drawn, then the rotor discs blended. Writes S0 = sqrt(exposed linear colour),
       S1.rgb = packed disparity (0 = nothing: sky), S1.a = 0.5 * is_leader + 0.49 * texturedness.
    2. post: the sensor (``SENSOR``). Depth: stereo noise on disparity, stereo shadows, edge and
       low-texture holes, range limits. Colour: optional rotational motion blur, vignetting, shot + read
       noise, gamma 2 and contrast. Writes RGBA8 colour, R32F depth in metres (0 = invalid), R8 mask.
    3. mask: the leader alone on a canvas with a shifted principal point (visible-fraction truth).

Real time (no supersampling, no motion blur) the scene shaders are compiled with ``DIRECT`` and apply
the sensor model themselves, writing final colour and depth (a third attachment) straight away: the
full-screen post pass, three texture reads per pixel, disappears. Only a scissored ``DEPTH_ONLY`` post
pass then adds depth-edge and stereo-shadow holes around near objects.
"""

from __future__ import annotations

#: The sensor model shared by the post pass and DIRECT scene shaders (needs ``u_fB`` declared first).
#: Its constants are folded on the CPU (:func:`sitl.render.sensor.sensor_uniforms`) so that a pixel costs
#: few ops.
SENSOR = """
// u_noise (depth only): g: white N(0,1) (a per-pixel coin), b: spatially correlated N(0,1) disparity
// noise (both stored as 8 (x - 0.5)); a: clumpy field, uniform on [0, 1]. Colour noise is hashed.
uniform sampler2D u_noise;
uniform ivec2 u_off;         // per-frame offset; p + u_off stays inside the field (no wrap to compute)
uniform uint u_seed;         // per-frame colour-noise seed
uniform vec4 u_vig;          // r = p u_vig.xy + u_vig.zw; r^2 = contrast vignetting / 4 (radius / half w)^2
uniform vec2 u_tone;         // (contrast, 0.45 (1 - contrast))
uniform vec3 u_noise_sd;     // contrast sd / NOISE_SUM_SD, sd = x + y / (v.g k + z): shot + read noise
uniform vec2 u_disp_noise;   // disparity noise (8 sigma, -4 sigma), px
uniform vec2 u_drange;       // valid true disparity (fB / z_max, fB / z_min), px
uniform vec2 u_hole_p;       // blob-hole threshold: p(textured) = x - y textured

vec4 sensor_noise(ivec2 p) { return texelFetch(u_noise, p + u_off, 0); }

// White luminance and chroma noise, each the sum of two bytes of a 32-bit hash of the pixel and the
// frame's seed (lowbias32): triangular on [0, 510], mean 255, sd NOISE_SUM_SD. A fifth of the cost of
// a texture fetch on llvmpipe.
vec2 colour_noise(ivec2 p) {
    uint h = (uint(p.x) | (uint(p.y) << 16)) ^ u_seed;
    h ^= h >> 16; h *= 0x7feb352du; h ^= h >> 15; h *= 0x846ca68bu; h ^= h >> 16;
    return vec2(uvec2(h & 255u, (h >> 16) & 255u) + uvec2((h >> 8) & 255u, h >> 24));
}

// Colour in the sqrt domain the scene writes (gamma 2, close to sRGB): vignetting, shot + read noise
// (shot noise is nearly constant in this domain, read noise grows in the dark; its level follows the
// green channel), contrast about 0.45. All of it is one multiply-add per channel after the set-up.
vec3 sensor_colour(vec3 v, vec2 lc) {
    vec2 r = gl_FragCoord.xy * u_vig.xy + u_vig.zw;
    float k = u_tone.x - dot(r, r);
    float sd = u_noise_sd.x + u_noise_sd.y / (v.g * k + u_noise_sd.z);
    // Luminance plus chroma along (1, -0.2, -1) / 2, both centred: 255 (1, 1, 1) + 255 (0.5, -0.1, -0.5).
    vec3 n = lc.y * vec3(0.5, -0.1, -0.5) + (lc.x - vec3(382.5, 229.5, 127.5));
    return v * k + (sd * n + u_tone.y);
}

// D400 stereo: noise on the true disparity d (px, 0 = nothing), range limits on the true disparity (a
// matcher's search range, so noise is never truncated), clumps of failed matches on low texture.
float sensor_depth(float d, float textured, vec4 nz) {
    float dn = nz.b * u_disp_noise.x + (d + u_disp_noise.y);
    bool valid = d >= u_drange.x && d <= u_drange.y && dn > 0.0 && nz.a >= u_hole_p.x - u_hole_p.y * textured;
    return valid ? u_fB / dn : 0.0;
}
"""


FULLSCREEN_VS = """
#version 330
in vec2 in_xy;
uniform float u_z;
void main() { gl_Position = vec4(in_xy, u_z, 1.0); }
"""

#: Offsets searched for stereo shadows, by the widest shadow expected (px); sparse beyond 4 px.
SHADOW_OFFSETS_PX: dict[int, tuple[int, ...]] = {
    2: (1, 2),
    4: (1, 2, 4),
    8: (1, 3, 6),
    16: (1, 3, 6, 10, 15),
    24: (1, 3, 6, 10, 15, 21),
}

_POST_BODY = (
    """
// Variant switches: SS (1 or 2), EDGES (0/1), N_SHADOW + SHADOW_OFFS, BLUR_N (0 = none),
// DEPTH_PASS (1: after a DIRECT scene pass, which wrote the final colour: only depth, from the scene's
// depth buffer (disparity) and colour alpha (leader, texturedness); scissored to where depth is valid).
uniform sampler2D u_col;
uniform sampler2D u_aux;
uniform sampler2D u_zbuf;    // DEPTH_PASS: the scene's window depth
uniform vec2 u_disp_from_z;  // DEPTH_PASS: disparity = window depth * x + y, px
uniform ivec2 u_size;        // output size, px
uniform float u_fB;          // focal length * baseline, px m
uniform mat3 u_H0;
uniform mat3 u_H1;
"""
    + SENSOR
    + """
#if DEPTH_PASS
layout(location = 0) out float o_depth;
#else
layout(location = 0) out vec4 o_rgb;
layout(location = 1) out float o_depth;
layout(location = 2) out float o_mask;
#endif

const vec3 DEC = vec3(255.0, 255.0 / 256.0, 255.0 / 65536.0);

#if DEPTH_PASS
float disp(ivec2 p) {
    return texelFetch(u_zbuf, min(p, u_size - 1), 0).r * u_disp_from_z.x + u_disp_from_z.y;
}
#else
float disp(ivec2 p) { return dot(texelFetch(u_aux, min(p, u_size - 1) * SS, 0).rgb, DEC); }
#endif

vec3 col_at(ivec2 q) {
#if SS == 1
    return texelFetch(u_col, q, 0).rgb;
#else
    ivec2 b = q * 2;
    return 0.25 * (texelFetch(u_col, b, 0).rgb + texelFetch(u_col, b + ivec2(1, 0), 0).rgb
        + texelFetch(u_col, b + ivec2(0, 1), 0).rgb + texelFetch(u_col, b + ivec2(1, 1), 0).rgb);
#endif
}

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    vec4 nz = sensor_noise(p);
#if DEPTH_PASS
    float d = disp(p);
    float ca = texelFetch(u_col, p, 0).a;
    float depth = sensor_depth(d, (ca - 0.5 * step(0.5, ca)) * (1.0 / 0.49), nz);
#else
    vec4 aux = texelFetch(u_aux, p * SS, 0);
    float d = dot(aux.rgb, DEC);
    float leader = step(0.5, aux.a);
    float depth = sensor_depth(d, (aux.a - 0.5 * leader) / 0.49, nz);
#endif
#if EDGES
    // Stereo shadow: the right imager sits at +x, so a surface k px to the right with k px more
    // disparity hides this point from it. Offsets are sparse beyond 4 px (see SHADOW_OFFSETS_PX).
    float dr = disp(p + ivec2(1, 0));
    float shadow = dr - d - 1.0;
#if N_SHADOW > 1
    const int OFFS[N_SHADOW] = int[N_SHADOW](SHADOW_OFFS);
    for (int i = 1; i < N_SHADOW; i++) {
        shadow = max(shadow, disp(p + ivec2(OFFS[i], 0)) - d - float(OFFS[i]));
    }
#endif
    // Depth edges: the matcher's window straddles two surfaces; three in four such pixels fail.
    float dd = disp(max(p - ivec2(0, 1), ivec2(0)));
    float jump = max(abs(dr - d), abs(dd - d));
    bool edge_hole = jump > max(0.5, 0.06 * d) && nz.g > 0.41625;   // N(0,1) > -0.67: 3 in 4
    if (shadow >= 0.0 || edge_hole) depth = 0.0;
#endif
    o_depth = depth;
#if !DEPTH_PASS
#if SS == 1
    o_mask = leader;
#else
    ivec2 b = p * 2;
    o_mask = 0.25 * (leader + step(0.5, texelFetch(u_aux, b + ivec2(1, 0), 0).a)
        + step(0.5, texelFetch(u_aux, b + ivec2(0, 1), 0).a)
        + step(0.5, texelFetch(u_aux, b + ivec2(1, 1), 0).a));
#endif
#if BLUR_N > 0
    vec3 pix = vec3(vec2(p), 1.0);
    vec3 a0 = u_H0 * pix;
    vec3 a1 = u_H1 * pix;
    vec2 qa = a0.xy / a0.z;
    vec2 qb = a1.xy / a1.z;
    vec3 v = vec3(0.0);
    for (int i = 0; i < BLUR_N; i++) {
        vec2 q = mix(qa, qb, (float(i) + 0.5) / float(BLUR_N));
        v += col_at(clamp(ivec2(floor(q + 0.5)), ivec2(0), u_size - 1));
    }
    v *= 1.0 / float(BLUR_N);
#else
    vec3 v = col_at(p);
#endif
    o_rgb = vec4(sensor_colour(v, colour_noise(p)), 1.0);
#endif
}
"""
)


def with_defines(source: str, **defines: int | str) -> str:
    """A shader source with ``#version 330`` and ``#define`` lines prepended."""
    head = "#version 330\n" + "".join(f"#define {k} {v}\n" for k, v in defines.items())
    return head + source


def post_fs(ss: int, edges: bool, shadow_px: int, blur_n: int, depth_pass: bool = False) -> str:
    """The post-pass source for one variant (``shadow_px`` must be a key of SHADOW_OFFSETS_PX)."""
    offs = SHADOW_OFFSETS_PX.get(shadow_px, (1,))
    return with_defines(
        _POST_BODY,
        SS=ss,
        EDGES=int(edges),
        N_SHADOW=len(offs),
        SHADOW_OFFS=", ".join(str(o) for o in offs),
        BLUR_N=blur_n,
        DEPTH_PASS=int(depth_pass),
    )


MASK_FS = """
#version 330
layout(location = 0) out float o_mask;
void main() { o_mask = 1.0; }
"""
