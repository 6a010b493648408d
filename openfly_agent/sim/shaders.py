"""GLSL 3.30 sources of the embedded renderer: instanced axis-aligned boxes and the textured ground.

Both programs write colour to attachment 0 and the instance id (building index + 1, 0 for anything
that is not a landmark) to the integer attachment 1. Facade windows, glass, foliage, road markings
and water are procedural in world coordinates, so there is no texture memory besides the ground map.
"""

from __future__ import annotations

_COMMON = """
uniform vec3 u_cam_pos;
uniform vec3 u_sky;
uniform float u_fog_density;   // 1 / metres
const vec3 SUN = normalize(vec3(0.45, 0.30, 0.84));

float hash21(vec2 p) {
    p = fract(p * vec2(123.34, 456.21));
    p += dot(p, p + 45.32);
    return fract(p.x * p.y);
}

float value_noise(vec2 p) {
    vec2 i = floor(p);
    vec2 f = fract(p);
    f = f * f * (3.0 - 2.0 * f);
    float a = hash21(i), b = hash21(i + vec2(1.0, 0.0));
    float c = hash21(i + vec2(0.0, 1.0)), d = hash21(i + vec2(1.0, 1.0));
    return mix(mix(a, b, f.x), mix(c, d, f.x), f.y);
}

vec3 apply_fog(vec3 color, vec3 world) {
    float fog = 1.0 - exp(-length(world - u_cam_pos) * u_fog_density);
    return mix(color, u_sky, fog);
}
"""

BOX_VERTEX = """
#version 330
uniform mat4 u_view_proj;
in vec3 in_corner;      // corner of the unit cube, components in {0, 1}
in vec3 in_lo;
in vec3 in_hi;
in vec3 in_color;
in int in_material;
in int in_instance;
out vec3 v_world;
flat out vec3 v_lo;
flat out vec3 v_hi;
flat out vec3 v_color;
flat out int v_material;
flat out int v_instance;

void main() {
    vec3 p = mix(in_lo, in_hi, in_corner);
    v_world = p;
    v_lo = in_lo;
    v_hi = in_hi;
    v_color = in_color;
    v_material = in_material;
    v_instance = in_instance;
    gl_Position = u_view_proj * vec4(p, 1.0);
}
"""

BOX_FRAGMENT = (
    """
#version 330
"""
    + _COMMON
    + """
in vec3 v_world;
flat in vec3 v_lo;
flat in vec3 v_hi;
flat in vec3 v_color;
flat in int v_material;
flat in int v_instance;
layout(location = 0) out vec4 f_color;
layout(location = 1) out int f_id;

// Outward normal of the axis-aligned face this fragment lies on.
vec3 face_normal(vec3 p) {
    vec3 to_lo = abs(p - v_lo), to_hi = abs(v_hi - p);
    vec3 d = min(to_lo, to_hi);
    vec3 s = 2.0 * vec3(lessThan(to_hi, to_lo)) - 1.0;
    if (d.z <= d.x && d.z <= d.y) return vec3(0.0, 0.0, s.z);
    if (d.x <= d.y) return vec3(s.x, 0.0, 0.0);
    return vec3(0.0, s.y, 0.0);
}

// Window grid: 3.2 m bays, 3.6 m floors; fades to its mean where a cell gets smaller than ~2 px.
vec3 windows(vec3 base, float s, float z, float glass) {
    vec2 cell = vec2(s / mix(3.2, 1.6, glass), z / 3.6);
    vec2 f = fract(cell);
    vec2 lo = mix(vec2(0.22, 0.28), vec2(0.06, 0.06), glass);
    vec2 hi = mix(vec2(0.78, 0.82), vec2(0.94, 0.94), glass);
    float win = step(lo.x, f.x) * step(f.x, hi.x) * step(lo.y, f.y) * step(f.y, hi.y);
    float mean = (hi.x - lo.x) * (hi.y - lo.y);
    vec2 fw = fwidth(cell);
    win = mix(mean, win, clamp(1.5 - 2.0 * max(fw.x, fw.y), 0.0, 1.0));
    float lit = 0.75 + 0.5 * hash21(floor(cell) + vec2(float(v_instance) * 7.1, 0.0));
    vec3 pane = mix(vec3(0.10, 0.14, 0.20), vec3(0.45, 0.58, 0.72), glass) * lit;
    // dark facades get light panes, so their windows still show
    if (dot(base, vec3(0.3, 0.59, 0.11)) < 0.25) pane = vec3(0.42, 0.50, 0.58) * lit;
    return mix(base, pane, win * mix(0.8, 0.55, glass));
}

void main() {
    vec3 n = face_normal(v_world);
    vec3 color = v_color;
    bool wall = n.z == 0.0;
    float s = n.x != 0.0 ? v_world.y : v_world.x;   // horizontal coordinate along a wall
    if (v_material == 1 && wall) {
        color = windows(color, s, v_world.z - v_lo.z, 0.0);
    } else if (v_material == 2 && wall) {
        color = windows(mix(color, vec3(0.40, 0.55, 0.70), 0.25), s, v_world.z - v_lo.z, 1.0);
    } else if (v_material == 3) {
        color *= 0.7 + 0.6 * value_noise(v_world.xy * 0.8 + v_world.z * 0.9);
    } else if (v_material == 4 && wall) {
        float band = step(0.5, fract((v_world.z - v_lo.z) / 3.0));
        color = mix(color, vec3(0.85, 0.15, 0.20), band);
    } else if (v_material == 5) {
        color = mix(vec3(0.95, 0.95, 0.95), color, step(0.5, fract(v_world.z / 4.0)));
    }
    if (!wall && (v_material == 1 || v_material == 2)) {
        color *= 0.82;  // roofs a little darker than facades
    }
    float light = 0.50 + 0.55 * max(dot(n, SUN), 0.0) + (n.z > 0.0 ? 0.0 : 0.06 * n.x);
    f_color = vec4(apply_fog(color * light, v_world), 1.0);
    f_id = v_instance;
}
"""
)

GROUND_VERTEX = """
#version 330
uniform mat4 u_view_proj;
in vec2 in_xy;
uniform float u_ground_z;
out vec3 v_world;

void main() {
    v_world = vec3(in_xy, u_ground_z);
    gl_Position = u_view_proj * vec4(v_world, 1.0);
}
"""

GROUND_FRAGMENT = (
    """
#version 330
"""
    + _COMMON
    + """
uniform sampler2D u_ground;     // RGB colour, alpha = region kind * 32 (see ground.py)
uniform vec2 u_map_origin;      // world x, y of texel (0, 0)'s corner
uniform vec2 u_map_size;        // metres covered by the map
uniform vec3 u_roads;           // (grid pitch, first road centre, road width); pitch 0 = no markings
in vec3 v_world;
layout(location = 0) out vec4 f_color;
layout(location = 1) out int f_id;

float road_offset(float c) {    // distance to the nearest road centre line along one axis
    float m = mod(c - u_roads.y + 0.5 * u_roads.x, u_roads.x) - 0.5 * u_roads.x;
    return abs(m);
}

void main() {
    vec2 uv = (v_world.xy - u_map_origin) / u_map_size;
    vec4 texel = texture(u_ground, uv);     // colour with baked grain (ground.py)
    int kind = int(texel.a * 255.0 / 32.0 + 0.5);
    vec3 color = texel.rgb;
    vec2 p = v_world.xy;
    if (kind == 1 && u_roads.x > 0.0) {                    // road: dashed centre lines
        float dx = road_offset(p.x), dy = road_offset(p.y);
        float half_road = 0.5 * u_roads.z;
        bool along_y = dx < 0.2 && dy > half_road;
        bool along_x = dy < 0.2 && dx > half_road;
        float dash = step(0.5, fract((along_y ? p.y : p.x) / 6.0));
        if ((along_x || along_y) && dash > 0.5) color = vec3(0.88, 0.82, 0.45);
    } else if (kind == 4) {                                // water ripples
        color *= 0.92 + 0.16 * sin(p.x * 0.35 + 0.6 * sin(p.y * 0.05));
    } else if (kind == 5 || kind == 2) {                   // plaza / sidewalk tiles
        vec2 f = abs(fract(p / 4.0) - 0.5);
        color *= max(f.x, f.y) > 0.46 ? 0.85 : 1.0;
    }
    float light = 0.50 + 0.55 * SUN.z;
    f_color = vec4(apply_fog(color * light, v_world), 1.0);
    f_id = 0;
}
"""
)
