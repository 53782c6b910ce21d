"""GLSL for the preview. GL 4.3 core: the deformation passes read storage buffers in the vertex stage.

Pass 1 (deform, transform feedback): ``p_v = n_v + sum_i c_i F_i[v]`` over the active fields only;
the fields are the rig's delta shapes, in-between residuals and corrective deltas (Lewis et al.
2014, §3.1-3.3), the coefficients ``c_i`` its weights, hat values and weight products.
Pass 2 (normals, transform feedback): area-weighted normal of each vertex's one-ring in the
deformed positions, so shading follows the deformed surface, not the neutral one.
Pass 3: lit draw of the deformed mesh under the head pose; then the marker overlay.
"""

DEFORM_VS = """
#version 430
in vec3 in_neutral;
layout(std430, binding = 0) readonly buffer Fields { float field[]; };
layout(std430, binding = 1) readonly buffer ActiveIdx { int active_idx[]; };
layout(std430, binding = 2) readonly buffer ActiveCoef { float active_coef[]; };
uniform int n_active;
uniform int n_vertices;
out vec3 out_pos;
void main() {
    int v3 = gl_VertexID * 3;
    vec3 d = vec3(0.0);
    for (int i = 0; i < n_active; ++i) {
        int base = active_idx[i] * n_vertices * 3 + v3;
        d += active_coef[i] * vec3(field[base], field[base + 1], field[base + 2]);
    }
    out_pos = in_neutral + d;
}
"""

NORMALS_VS = """
#version 430
layout(std430, binding = 3) readonly buffer Pos { float pos[]; };
layout(std430, binding = 4) readonly buffer RingStart { int ring_start[]; };
layout(std430, binding = 5) readonly buffer Ring { int ring[]; };
out vec3 out_normal;
vec3 P(int i) { return vec3(pos[3 * i], pos[3 * i + 1], pos[3 * i + 2]); }
void main() {
    int v = gl_VertexID;
    vec3 a = P(v);
    vec3 n = vec3(0.0);
    for (int k = ring_start[v]; k < ring_start[v + 1]; ++k) {
        n += cross(P(ring[2 * k]) - a, P(ring[2 * k + 1]) - a);
    }
    float l = length(n);
    out_normal = l > 0.0 ? n / l : vec3(0.0, 0.0, 1.0);
}
"""

# A do-nothing fragment stage for the transform-feedback passes (rasteriser is discarded).
NULL_FS = """
#version 430
out vec4 f_color;
void main() { f_color = vec4(0.0); }
"""

MESH_VS = """
#version 430
in vec3 in_pos;
in vec3 in_normal;
uniform mat4 model;
uniform mat4 view_proj;
out vec3 v_world;
out vec3 v_normal;
void main() {
    vec4 w = model * vec4(in_pos, 1.0);
    v_world = w.xyz;
    v_normal = mat3(model) * in_normal;  // rigid motion times a uniform scale: no inverse-transpose needed
    gl_Position = view_proj * w;
}
"""

MESH_FS = """
#version 430
in vec3 v_world;
in vec3 v_normal;
uniform vec3 eye;
uniform vec3 albedo;
out vec4 f_color;
vec3 light(vec3 n, vec3 v, vec3 dir, vec3 colour, float shininess) {
    vec3 l = normalize(dir);
    float diff = max(dot(n, l), 0.0);
    float spec = diff > 0.0 ? pow(max(dot(n, normalize(l + v)), 0.0), shininess) : 0.0;
    return colour * (diff * albedo + 0.12 * spec);
}
void main() {
    vec3 n = normalize(v_normal);
    if (!gl_FrontFacing) n = -n;  // two-sided: open meshes and either winding shade the visible side
    vec3 v = normalize(eye - v_world);
    vec3 c = albedo * mix(vec3(0.10, 0.09, 0.10), vec3(0.22, 0.22, 0.25), 0.5 + 0.5 * n.y);  // hemisphere
    c += light(n, v, vec3(-0.65, 0.50, 0.55), vec3(0.92, 0.88, 0.82), 24.0);  // key
    c += light(n, v, vec3(0.75, 0.05, 0.50), vec3(0.26, 0.30, 0.38), 12.0);   // fill
    c += 0.25 * pow(1.0 - max(dot(n, v), 0.0), 3.0) * vec3(0.6, 0.7, 0.9);     // rim
    f_color = vec4(pow(clamp(c, 0.0, 1.0), vec3(1.0 / 2.2)), 1.0);
}
"""

OVERLAY_VS = """
#version 430
in vec3 in_pos;
in vec3 in_colour;
uniform mat4 view_proj;
uniform float point_size;
out vec3 v_colour;
void main() {
    v_colour = in_colour;
    gl_PointSize = point_size;
    gl_Position = view_proj * vec4(in_pos, 1.0);
}
"""

OVERLAY_FS = """
#version 430
in vec3 v_colour;
uniform bool round_points;
out vec4 f_color;
void main() {
    if (round_points && length(gl_PointCoord - vec2(0.5)) > 0.5) discard;
    f_color = vec4(v_colour, 1.0);
}
"""
