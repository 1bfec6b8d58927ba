"""GLSL 3.30 sources of the renderer's passes, shaped by what Mesa llvmpipe is fast and slow at.

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
    2. post: the sensor (``_SENSOR``). Depth: stereo noise on disparity, stereo shadows, edge and
       low-texture holes, range limits. Colour: optional rotational motion blur, vignetting, shot + read
       noise, gamma 2 and contrast. Writes RGBA8 colour, R32F depth in metres (0 = invalid), R8 mask.
    3. mask: the leader alone on a canvas with a shifted principal point (visible-fraction truth).

Real time (no supersampling, no motion blur) the scene shaders are compiled with ``DIRECT`` and apply
the sensor model themselves, writing final colour and depth (a third attachment) straight away: the
full-screen post pass, three texture reads per pixel, disappears. Only a scissored ``DEPTH_ONLY`` post
pass then adds depth-edge and stereo-shadow holes around near objects.
"""

from __future__ import annotations

_TEX_LOD = """
uniform sampler2D u_tex;
// t in texels of the 1024^2 pattern texture; GL picks the mip level, nearest filtering (cheap on llvmpipe).
vec4 tex_lod(vec2 t) { return texture(u_tex, t * (1.0 / 1024.0)); }
"""

#: The sensor model shared by the post pass and DIRECT scene shaders (needs ``u_fB`` declared first).
_SENSOR = """
// r: white N(0,1) luminance noise, g: white N(0,1) chroma noise (also a per-pixel coin), b: spatially
// correlated N(0,1) disparity noise (all stored as 8 (x - 0.5)); a: clumpy field, uniform on [0, 1].
uniform sampler2D u_noise;
uniform ivec2 u_off;
uniform vec2 u_half_size;    // output half size, px
uniform vec3 u_noise_sd;     // colour noise sd in the sqrt domain: sd = x + y / (v + z), v = sqrt(linear)
uniform float u_vignette;
uniform float u_contrast;
uniform float u_subpix;      // disparity noise sigma, px
uniform vec2 u_zrange;       // valid depth, m
uniform vec2 u_hole_p;       // blob-hole probability: (floor, extra at zero texture)

vec4 sensor_noise(ivec2 p) { return texelFetch(u_noise, (p + u_off) & 1023, 0); }

// Colour in the sqrt domain the scene writes (gamma 2, close to sRGB): vignetting, shot + read noise
// (shot noise is nearly constant in this domain), contrast.
vec3 sensor_colour(vec3 v, vec4 nz) {
    vec3 n = 8.0 * (nz.rgb - 0.5);
    vec2 r = (gl_FragCoord.xy - u_half_size) / u_half_size.x;
    v *= 1.0 - u_vignette * 0.25 * dot(r, r);
    v += (u_noise_sd.x + u_noise_sd.y / (v + u_noise_sd.z)) * (n.r + 0.5 * n.g * vec3(1.0, -0.2, -1.0));
    return (v - 0.45) * u_contrast + 0.45;
}

// D400 stereo: noise on the true disparity d (px, 0 = nothing), range limits on the true disparity (a
// matcher's search range, so noise is never truncated), clumps of failed matches on low texture.
float sensor_depth(float d, float textured, vec4 nz) {
    float dn = d + u_subpix * 8.0 * (nz.b - 0.5);
    bool valid = d >= u_fB / u_zrange.y && d <= u_fB / u_zrange.x && dn > 0.0
        && nz.a >= u_hole_p.x + u_hole_p.y * (1.0 - textured);
    return valid ? u_fB / dn : 0.0;
}
"""

SCENE_VS = """
#version 330
uniform mat4 u_clip_from_ned;
uniform mat4 u_ned_from_model;
in vec3 in_pos;
in vec3 in_nrm;
in vec3 in_rgb;
in vec2 in_uv;
in float in_kind;
out vec3 v_p;
out vec3 v_n;
out vec3 v_rgb;
out vec2 v_uv;
flat out int v_kind;
flat out float v_param;
void main() {
    vec4 pw = u_ned_from_model * vec4(in_pos, 1.0);
    v_p = pw.xyz;
    v_n = mat3(u_ned_from_model) * in_nrm;
    v_rgb = in_rgb;
    v_uv = in_uv;
    v_kind = int(floor(in_kind));
    v_param = fract(in_kind);
    gl_Position = u_clip_from_ned * pw;
}
"""

_SCENE_HEAD = (
    """
uniform vec3 u_cam_ned;
uniform vec3 u_sun_dir;
uniform vec3 u_sun_rgb;
uniform vec3 u_sky_rgb;
uniform vec3 u_bounce_rgb;
uniform vec3 u_fog_rgb;
uniform float u_fog_density;
uniform vec3 u_gain_rgb;
uniform vec3 u_glare_rgb;   // veiling glare from a sun near the view (scattered in the lens)
uniform float u_leader;
uniform float u_fB;   // focal length * baseline at output resolution, px m
#if DIRECT
"""
    + _SENSOR
    + """
#endif
in vec3 v_p;
in vec3 v_n;
in vec3 v_rgb;
in vec2 v_uv;
flat in int v_kind;
flat in float v_param;
layout(location = 0) out vec4 o_col;
layout(location = 1) out vec4 o_aux;
#if DIRECT
layout(location = 2) out float o_depth;
#endif

vec3 pack_disparity(float d) {
    // d in [0, 256) px -> 8.16 fixed point in three bytes; decoded as dot(rgb, (255, 255/256, 255/65536)).
    d = clamp(d, 0.0, 255.99);
    float hi = floor(d);
    float r1 = (d - hi) * 256.0;
    float mid = floor(r1);
    return vec3(hi, mid, (r1 - mid) * 256.0) / 255.0;
}

vec3 ambient(vec3 n) { return mix(u_bounce_rgb, u_sky_rgb, 0.5 - 0.5 * n.z); }

float spec32(float x) {
    x = max(x, 0.0);
    x *= x; x *= x; x *= x; x *= x; x *= x;
    return x;
}

void emit(vec3 col, float alpha, float textured, float dist) {
    float fog = exp(-u_fog_density * dist);
    col = mix(u_fog_rgb, col, fog) + u_glare_rgb;
    vec3 v = sqrt(clamp(col * u_gain_rgb, 0.0, 1.0));
    float d = u_fB * gl_FragCoord.w;
    textured *= fog;
#if DIRECT
    vec4 nz = sensor_noise(ivec2(gl_FragCoord.xy));
    v = sensor_colour(v, nz);
    o_depth = sensor_depth(d, textured, nz);
#endif
    o_col = vec4(v, alpha);
    o_aux = vec4(pack_disparity(d), 0.5 * u_leader + 0.49 * textured);
}
"""
)

#: Ground, per frame: the baked material texture (1024 m period) times fine detail, lit as flat.
SCENE_GROUND_FS = (
    _SCENE_HEAD
    + """
uniform sampler2D u_tex;
uniform sampler2D u_ground;     // sqrt(albedo), texturedness; GROUND_PERIOD_M period, mipmapped
uniform vec3 u_ground_light;    // irradiance on flat ground: sun * cos(zenith) + sky
uniform vec2 u_ground_lod;      // mip level at 1 m distance of the ground and the detail textures
void main() {
    float dist = length(u_cam_ned - v_p);
    // A flat ground seen from height h: a pixel's footprint along the view is dist^2 / (f h), so the
    // mip level is 2 log2(dist) + const (implicit derivatives cost more than the fetch on llvmpipe).
    float l = 2.0 * log2(dist);
    vec4 g = textureLod(u_ground, v_p.xy * (1.0 / 1024.0), l + u_ground_lod.x);
    float det = textureLod(u_tex, v_p.xy * (25.0 / 1024.0), l + u_ground_lod.y).b;
    emit(g.rgb * g.rgb * (0.7 + 0.6 * det) * u_ground_light, 1.0, g.a, dist);
}
"""
)

#: Bakes the ground material texture once per world: large patches of up to four materials, field
#: rows and a road, all periodic over 1024 m so the texture tiles without seams.
GROUND_BAKE_FS = (
    """
#version 330
"""
    + _TEX_LOD
    + """
uniform vec3 u_ground_rgb[4];
uniform vec4 u_ground_texture;
uniform int u_ground_n;
uniform vec4 u_road;       // (axis 0 = along north / 1 = along east, offset m, half width m, 0)
uniform vec2 u_rows;       // field rows: (axis, rows per period)
uniform float u_texel_m;
layout(location = 0) out vec4 o_ground;
void main() {
    vec2 p = (gl_FragCoord.xy - 0.5) * u_texel_m;   // metres over one 1024 m period
    vec4 macro = tex_lod(p);                         // 1024 texels per 1024 m: seamless
    float s = macro.r * float(u_ground_n) - 0.5;
    int i0 = clamp(int(floor(s)), 0, u_ground_n - 1);
    int i1 = min(i0 + 1, u_ground_n - 1);
    float w = smoothstep(0.4, 0.6, fract(s));
    vec3 albedo = mix(u_ground_rgb[i0], u_ground_rgb[i1], w);
    float textured = mix(u_ground_texture[i0], u_ground_texture[i1], w);
    albedo *= 0.8 + 0.4 * macro.g;
    float across = u_rows.x < 0.5 ? p.y : p.x;
    float rc = across * u_rows.y / 1024.0;
    albedo *= 1.0 - 0.25 * smoothstep(0.55, 0.75, macro.g) * step(0.5, fract(rc));
    float rdist = abs((u_road.x < 0.5 ? p.y : p.x) - u_road.y);
    float on_road = 1.0 - smoothstep(u_road.z - u_texel_m, u_road.z + u_texel_m, rdist);
    on_road *= step(0.01, u_road.z);
    float line = (1.0 - smoothstep(0.1, 0.1 + u_texel_m, abs(rdist - u_road.z + 0.4))) * on_road;
    albedo = mix(albedo, vec3(0.07, 0.07, 0.075) * (0.85 + 0.3 * macro.a), on_road);
    albedo = mix(albedo, vec3(0.6), line);
    textured = mix(textured, 0.5, on_road);
    o_ground = vec4(sqrt(clamp(albedo, 0.0, 1.0)), textured);
}
"""
)

#: Everything opaque that is not ground or foliage: the leader, buildings (with windows), poles,
#: distractors. Material differences are arithmetic, not branches.
SCENE_GENERIC_FS = (
    _SCENE_HEAD
    + """
void main() {
    vec3 to_cam = u_cam_ned - v_p;
    float dist = length(to_cam);
    vec3 view = to_cam / dist;
    vec3 n = normalize(v_n);
    n = dot(n, view) < 0.0 ? -n : n;
    float glossy = float(v_kind == 1);
    float metal = float(v_kind == 8);
    float wall = float(v_kind == 3);
    float emissive = float(v_kind == 10);
    vec2 g = vec2(v_uv.x / 3.0, v_uv.y / 3.2);
    vec2 f = fract(g);
    float aa = clamp(1.0 - 2.0 * max(fwidth(g.x), fwidth(g.y)), 0.0, 1.0);
    float win = wall * step(0.28, f.x) * step(f.x, 0.72) * step(0.3, f.y) * step(f.y, 0.78) * step(1.0, g.y);
    vec3 albedo = mix(v_rgb, vec3(0.04, 0.05, 0.06), win * aa + wall * (1.0 - aa) * 0.2);
    float spec = 0.35 * glossy + 0.6 * metal + 0.6 * win * aa;
    float ndl = max(dot(n, u_sun_dir), 0.0);
    vec3 col = albedo * (u_sun_rgb * ndl + ambient(n));
    vec3 h = normalize(u_sun_dir + view);
    float fres = 1.0 - max(dot(n, view), 0.0);
    fres *= fres; fres *= fres;
    col += spec * (u_sun_rgb * spec32(dot(n, h)) * step(0.0, ndl) + (0.15 + 0.6 * fres) * ambient(n));
    col = mix(col, v_rgb, emissive);
    emit(col, 1.0, mix(0.85, 0.6, max(wall, glossy)), dist);
}
"""
)

#: Tree crowns (FOLIAGE, sparsity in the kind's fraction) and the horizon forest band (DISTANT).
SCENE_FOLIAGE_FS = (
    _SCENE_HEAD
    + _TEX_LOD
    + """
void main() {
    vec3 to_cam = u_cam_ned - v_p;
    float dist = length(to_cam);
    vec3 view = to_cam / dist;
    vec3 n = normalize(v_n);
    n = dot(n, view) < 0.0 ? -n : n;
    vec4 t1 = tex_lod(vec2(v_p.x + 0.6 * v_p.z, v_p.y - 0.6 * v_p.z) / 0.06);
    vec4 t2 = tex_lod(vec2(v_p.x - 0.5 * v_p.z, v_p.y + 0.8 * v_p.z) / 0.5);
    float leaf = 0.5 * t1.b + 0.5 * t2.g;
    float rim = 1.0 - abs(dot(n, view));
    float crown_cut = leaf - (v_param * 0.9 + 0.55 * rim * rim);
    // Horizon forest: crowns a few metres wide cut into the top third of the band (coarse noise
    // along the ring, so it survives the distance).
    vec4 t3 = tex_lod(vec2(v_uv.x / 2.5, 40.0 + 0.3 * v_uv.y));
    float band_cut = 0.62 + 0.38 * t3.b - v_uv.y;
    if ((v_kind == 9 ? band_cut : crown_cut) < 0.0) discard;
    vec3 albedo = v_rgb * (0.55 + 0.9 * leaf);
    vec3 col = albedo * (u_sun_rgb * max(dot(n, u_sun_dir), 0.0) + ambient(n)) * (0.75 + 0.25 * leaf);
    emit(col, 1.0, 1.0, dist);
}
"""
)

#: Spinning prop discs: translucent, the two blades smeared by the exposure.
SCENE_ROTOR_FS = (
    _SCENE_HEAD
    + """
uniform float u_rotor_phase;
uniform float u_blade_vis;
void main() {
    vec3 to_cam = u_cam_ned - v_p;
    float dist = length(to_cam);
    float r = length(v_uv);
    float c = cos(atan(v_uv.y, v_uv.x) - u_rotor_phase);
    float blades = c * c;
    blades *= blades; blades *= blades; blades *= blades;
    float chord = (1.0 - smoothstep(0.85, 1.0, r)) * (0.7 + 0.3 * (1.0 - r));
    float alpha = clamp(mix(0.28, 0.95 * blades, u_blade_vis) * chord + 0.6 * step(r, 0.1), 0.0, 1.0);
    vec3 col = v_rgb * (u_sun_rgb * 0.5 + ambient(vec3(0.0, 0.0, 1.0)));
    emit(col, alpha, 0.9, dist);
}
"""
)

FULLSCREEN_VS = """
#version 330
in vec2 in_xy;
uniform float u_z;
void main() { gl_Position = vec4(in_xy, u_z, 1.0); }
"""

#: Bakes one face of the sky cube map once per world: gradient, sun, glow, haze and a cloud layer.
#: Stored as sqrt(radiance / SKY_SCALE) so an RGBA8 face keeps the dark dusk sky smooth.
SKY_BAKE_FS = (
    """
#version 330
"""
    + _TEX_LOD
    + """
uniform vec3 u_sun_dir;
uniform vec3 u_sun_rgb;
uniform float u_sun_cos;
uniform vec3 u_zenith_rgb;
uniform vec3 u_horizon_rgb;
uniform vec3 u_glow_rgb;
uniform vec3 u_haze_rgb;
uniform vec3 u_cloud_lit_rgb;
uniform vec3 u_cloud_dark_rgb;
uniform vec4 u_cloud;      // (altitude m, texel size m, coverage threshold low, high)
uniform vec2 u_cloud_off;  // texels
uniform mat3 u_dir_from_st;   // cube face (s, t, 1) in [-1, 1] -> direction (GL cube-map convention)
uniform float u_face_px;
uniform float u_sky_scale;
uniform vec3 u_fog_rgb;
uniform float u_fog_density;
const float FOG_LAYER_M = 300.0;   // fog thickness for upward rays
layout(location = 0) out vec4 o_sky;
void main() {
    vec2 st = 2.0 * gl_FragCoord.xy / u_face_px - 1.0;
    vec3 d = normalize(u_dir_from_st * vec3(st, 1.0));
    float el = -d.z;
    float mu = dot(d, u_sun_dir);
    float e = clamp(el, 0.0, 1.0);
    vec3 c = mix(u_horizon_rgb, u_zenith_rgb, sqrt(e));
    c += u_glow_rgb * exp(5.0 * (mu - 1.0) - 6.0 * e);
    c += u_sun_rgb * (0.02 * exp(30.0 * (mu - 1.0)) + 0.25 * exp(800.0 * (mu - 1.0)));
    c += u_sun_rgb * 30.0 * step(u_sun_cos, mu);
    float t = u_cloud.x / max(el, 0.004);
    vec2 q = d.xy * t / u_cloud.y + u_cloud_off;
    vec4 nz = tex_lod(q);
    vec4 fine = tex_lod(q * 3.7 + 17.0);
    // Shape from the large scales, a little fine detail on the edges; thins out towards the horizon.
    float dens = 0.8 * nz.r + 0.12 * nz.g + 0.08 * fine.g;
    float cov = smoothstep(u_cloud.z, u_cloud.w, dens) * smoothstep(0.0, 0.12, el);
    float thick = clamp((dens - u_cloud.z) / max(1.0 - u_cloud.z, 0.05), 0.0, 1.0) * (0.7 + 0.3 * fine.r);
    vec3 cl = mix(u_cloud_lit_rgb, u_cloud_dark_rgb, thick);
    cl += u_sun_rgb * 0.15 * exp(8.0 * (mu - 1.0)) * (1.0 - thick);
    c = mix(c, cl, cov);
    c = mix(u_haze_rgb, c, exp(60.0 * min(el, 0.0)));
    // Fog veils the sky too: the path through a FOG_LAYER_M-deep layer, long towards the horizon.
    c = mix(u_fog_rgb, c, exp(-u_fog_density * min(FOG_LAYER_M / max(el, 0.01), 20000.0)));
    o_sky = vec4(sqrt(clamp(c / u_sky_scale, 0.0, 1.0)), 1.0);
}
"""
)

#: The sky per frame: one cube-map lookup where nothing else was drawn.
SKY_FS = (
    """
uniform samplerCube u_sky;
uniform mat3 u_ned_from_pix;   // R_ned_cam * K^-1 at the framebuffer's scale
uniform vec3 u_gain_rgb;       // exposure * white balance * SKY_SCALE
uniform vec3 u_glare_rgb;      // veiling glare, divided by SKY_SCALE
uniform float u_fB;
#if DIRECT
"""
    + _SENSOR
    + """
layout(location = 2) out float o_depth;
#endif
layout(location = 0) out vec4 o_col;
layout(location = 1) out vec4 o_aux;
void main() {
    // Level 0: face texels are about a pixel wide; implicit LOD on a cube costs ~3x the lookup here.
    vec3 s = textureLod(u_sky, u_ned_from_pix * vec3(gl_FragCoord.xy - 0.5, 1.0), 0.0).rgb;
    vec3 v = sqrt(min((s * s + u_glare_rgb) * u_gain_rgb, 1.0));
#if DIRECT
    v = sensor_colour(v, sensor_noise(ivec2(gl_FragCoord.xy)));
    o_depth = 0.0;
#endif
    o_col = vec4(v, 1.0);
    o_aux = vec4(0.0);
}
"""
)

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
// DEPTH_ONLY (1: write only depth, location 0; the colour and mask came from a DIRECT scene pass).
uniform sampler2D u_col;
uniform sampler2D u_aux;
uniform ivec2 u_size;        // output size, px
uniform float u_fB;          // focal length * baseline, px m
uniform mat3 u_H0;
uniform mat3 u_H1;
"""
    + _SENSOR
    + """
#if DEPTH_ONLY
layout(location = 0) out float o_depth;
#else
layout(location = 0) out vec4 o_rgb;
layout(location = 1) out float o_depth;
layout(location = 2) out float o_mask;
#endif

const vec3 DEC = vec3(255.0, 255.0 / 256.0, 255.0 / 65536.0);

float disp(ivec2 p) { return dot(texelFetch(u_aux, min(p, u_size - 1) * SS, 0).rgb, DEC); }

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
    vec4 aux = texelFetch(u_aux, p * SS, 0);
    float d = dot(aux.rgb, DEC);
    float leader = step(0.5, aux.a);
    float depth = sensor_depth(d, (aux.a - 0.5 * leader) / 0.49, nz);
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
    bool edge_hole = jump > max(0.5, 0.06 * d) && 8.0 * (nz.g - 0.5) > -0.67;
    if (shadow >= 0.0 || edge_hole) depth = 0.0;
#endif
    o_depth = depth;
#if !DEPTH_ONLY
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
    o_rgb = vec4(sensor_colour(v, nz), 1.0);
#endif
}
"""
)


def with_defines(source: str, **defines: int | str) -> str:
    """A shader source with ``#version 330`` and ``#define`` lines prepended."""
    head = "#version 330\n" + "".join(f"#define {k} {v}\n" for k, v in defines.items())
    return head + source


def post_fs(ss: int, edges: bool, shadow_px: int, blur_n: int, depth_only: bool = False) -> str:
    """The post-pass source for one variant (``shadow_px`` must be a key of SHADOW_OFFSETS_PX)."""
    offs = SHADOW_OFFSETS_PX.get(shadow_px, (1,))
    return with_defines(
        _POST_BODY,
        SS=ss,
        EDGES=int(edges),
        N_SHADOW=len(offs),
        SHADOW_OFFS=", ".join(str(o) for o in offs),
        BLUR_N=blur_n,
        DEPTH_ONLY=int(depth_only),
    )


MASK_FS = """
#version 330
layout(location = 0) out float o_mask;
void main() { o_mask = 1.0; }
"""
