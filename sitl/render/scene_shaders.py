"""GLSL 3.30 sources of the renderer's scene pass (see :mod:`sitl.render.shaders` for the passes).

The scene vertex shader; one fragment program per material group (ground, generic, foliage, rotor
discs) sharing a head that shades, fogs and exposes, and, DIRECT, applies the sensor model; the sky
(a skybox at output resolution, a cube map when supersampled); and the bakes, once per world, of the
periodic ground texture and the sky's faces.
"""

from __future__ import annotations

from sitl.render.shaders import SENSOR

_TEX_LOD = """
uniform sampler2D u_tex;
// t in texels of the 1024^2 pattern texture; GL picks the mip level, nearest filtering (cheap on llvmpipe).
vec4 tex_lod(vec2 t) { return texture(u_tex, t * (1.0 / 1024.0)); }
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
uniform vec3 u_gain_rgb;    // exposure * white balance
uniform vec3 u_glare_rgb;   // veiling glare from a sun near the view (scattered in the lens), times gain
uniform float u_leader;
uniform float u_fB;   // focal length * baseline at output resolution, px m
#if DIRECT
"""
    + SENSOR
    + """
#endif
in vec3 v_p;
in vec3 v_n;
in vec3 v_rgb;
in vec2 v_uv;
flat in int v_kind;
flat in float v_param;
uniform float u_blend_alpha;   // 1: alpha is the opacity to blend with (rotor discs, first pass)
layout(location = 0) out vec4 o_col;
#if !DIRECT
layout(location = 1) out vec4 o_aux;
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

// alpha: the rotor discs' opacity (blended while u_blend_alpha = 1). DIRECT otherwise writes
// 0.5 (1 - leader) + 0.49 texturedness into colour alpha for the depth pass and the leader mask.
void emit(vec3 col, float alpha, float textured, float dist) {
    float fog = exp(-u_fog_density * dist);
    col = mix(u_fog_rgb, col, fog);
    vec3 v = sqrt(min(col * u_gain_rgb + u_glare_rgb, 1.0));   // col >= 0
    textured *= fog;
#if DIRECT
    float a = 0.5 - 0.5 * u_leader + 0.49 * textured;
    o_col = vec4(sensor_colour(v, colour_noise(ivec2(gl_FragCoord.xy))), mix(a, alpha, u_blend_alpha));
#else
    o_col = vec4(v, alpha);
    o_aux = vec4(pack_disparity(u_fB * gl_FragCoord.w), 0.5 * u_leader + 0.49 * textured);
#endif
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
uniform vec2 u_ground_lod_k;    // FILTERED == 0: 2^(u_ground_lod + 0.5)
void main() {
    vec3 to_cam = u_cam_ned - v_p;
    float dist2 = dot(to_cam, to_cam);
    // A flat ground seen from height h: a pixel's footprint along the view is dist^2 / (f h), so the
    // mip level is log2(dist^2) + const (implicit derivatives cost more than the fetch on llvmpipe).
#if FILTERED
    float l = log2(dist2);
    vec4 g = textureLod(u_ground, v_p.xy * (1.0 / 1024.0), l + u_ground_lod.x);
    float det = textureLod(u_tex, v_p.xy * (25.0 / 1024.0), l + u_ground_lod.y).b;
#else
    // Nearest mip level = the float exponent of dist^2 2^(lod + 0.5); fetch the texel by hand (texture
    // wrap is a mask at power-of-two sizes): a third cheaper than textureLod with a per-pixel level.
    // GROUND_TEX_PX (2^GROUND_LEVELS) texels per GROUND_PERIOD_M; the detail pattern: 1024 per 40.96 m.
    int l0 = clamp((floatBitsToInt(dist2 * u_ground_lod_k.x) >> 23) - 127, 0, GROUND_LEVELS);
    int l1 = clamp((floatBitsToInt(dist2 * u_ground_lod_k.y) >> 23) - 127, 0, 10);
    ivec2 t0 = ivec2(floor(v_p.xy * (float(1 << GROUND_LEVELS) / GROUND_PERIOD_M)));
    ivec2 t1 = ivec2(floor(v_p.xy * 25.0));
    vec4 g = texelFetch(u_ground, (t0 >> l0) & (((1 << GROUND_LEVELS) >> l0) - 1), l0);
    float det = texelFetch(u_tex, (t1 >> l1) & ((1024 >> l1) - 1), l1).b;
#endif
    emit(g.rgb * g.rgb * (0.7 + 0.6 * det) * u_ground_light, 1.0, g.a, sqrt(dist2));
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
#: distractors. Material differences are arithmetic, not branches. Compiled with ``DIFFUSE`` for the
#: world's plain, roof and bark surfaces (trunks, poles, roofs, hills), which have no windows or gloss.
SCENE_GENERIC_FS = (
    _SCENE_HEAD
    + """
void main() {
#if DIFFUSE
    vec3 to_cam = u_cam_ned - v_p;
    vec3 n = normalize(v_n);
    n = dot(n, to_cam) < 0.0 ? -n : n;
    emit(v_rgb * (u_sun_rgb * max(dot(n, u_sun_dir), 0.0) + ambient(n)), 1.0, 0.85, length(to_cam));
#else
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
#endif
}
"""
)

#: Tree crowns (FOLIAGE, sparsity in the kind's fraction), or with ``BAND`` the horizon forest band
#: (DISTANT): one texture lookup there, where the crowns' fine leaf pattern is sub-pixel anyway.
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
#if BAND
    // Horizon forest: crowns a few metres wide cut into the top third of the band (coarse noise
    // along the ring, so it survives the distance); the crowns' 0.5 m leaf blotches from the same
    // lookup, their 6 cm leaves averaged.
    vec4 t3 = tex_lod(vec2(v_uv.x / 2.5, 40.0 + 0.3 * v_uv.y));
    if (0.62 + 0.38 * t3.b - v_uv.y < 0.0) discard;
    float leaf = 0.25 + 0.5 * t3.g;
#else
    vec4 t1 = tex_lod(vec2(v_p.x + 0.6 * v_p.z, v_p.y - 0.6 * v_p.z) / 0.06);
    vec4 t2 = tex_lod(vec2(v_p.x - 0.5 * v_p.z, v_p.y + 0.8 * v_p.z) / 0.5);
    float leaf = 0.5 * t1.b + 0.5 * t2.g;
    float rim = 1.0 - abs(dot(n, view));
    if (leaf - (v_param * 0.9 + 0.55 * rim * rim) < 0.0) discard;
#endif
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
uniform vec2 u_face_org;      // window position of the face's corner (faces share one atlas)
uniform float u_sky_scale;
uniform vec3 u_fog_rgb;
uniform float u_fog_density;
const float FOG_LAYER_M = 300.0;   // fog thickness for upward rays
layout(location = 0) out vec4 o_sky;
void main() {
    vec2 st = 2.0 * (gl_FragCoord.xy - u_face_org) / u_face_px - 1.0;
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

#: The sky per frame, supersampled (datasets): one filtered cube-map lookup where nothing else was drawn.
SKY_FS = """
#version 330
uniform samplerCube u_sky;
uniform mat3 u_ned_from_pix;   // R_ned_cam * K^-1 at the framebuffer's scale
uniform vec3 u_gain_rgb;       // exposure * white balance * SKY_SCALE
uniform vec3 u_glare_rgb;      // veiling glare times exposure * white balance
layout(location = 0) out vec4 o_col;
layout(location = 1) out vec4 o_aux;
void main() {
    vec3 s = textureLod(u_sky, u_ned_from_pix * vec3(gl_FragCoord.xy - 0.5, 1.0), 0.0).rgb;
    o_col = vec4(sqrt(min(s * s * u_gain_rgb + u_glare_rgb, 1.0)), 1.0);
    o_aux = vec4(0.0);
}
"""

#: The sky at output resolution: a cube around the camera, each face textured from its tile of the
#: baked atlas. The rasteriser interpolates the face coordinates (exact: a face is a plane), so a
#: pixel costs one ``texelFetch`` instead of a direction and a cube-map lookup (3x cheaper on llvmpipe).
SKYBOX_VS = """
#version 330
uniform mat4 u_clip_from_ned;
in vec3 in_dir;    // a cube corner, NED (only its direction matters)
in vec2 in_uv;     // its atlas texel coordinates
out vec2 v_uv;
void main() {
    v_uv = in_uv;
    gl_Position = (u_clip_from_ned * vec4(in_dir, 0.0)).xyww;   // at infinity: window depth 1
}
"""

SKYBOX_FS = (
    """
uniform sampler2D u_sky_atlas;
uniform vec3 u_gain_rgb;       // exposure * white balance * SKY_SCALE
uniform vec3 u_glare_rgb;      // veiling glare times exposure * white balance
uniform float u_fB;
#if DIRECT
"""
    + SENSOR
    + """
#else
layout(location = 1) out vec4 o_aux;
#endif
layout(location = 0) out vec4 o_col;
in vec2 v_uv;
void main() {
    vec3 s = texelFetch(u_sky_atlas, ivec2(v_uv), 0).rgb;
    vec3 v = sqrt(min(s * s * u_gain_rgb + u_glare_rgb, 1.0));
#if DIRECT
    o_col = vec4(sensor_colour(v, colour_noise(ivec2(gl_FragCoord.xy))), 0.5);   // not leader, no texture
#else
    o_col = vec4(v, 1.0);
    o_aux = vec4(0.0);
#endif
}
"""
)
