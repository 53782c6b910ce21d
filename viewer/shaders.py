"""GLSL for the preview. GL 4.3 core: the deformation passes read storage buffers in the vertex stage.

Pass 1 (deform, transform feedback): ``p_v = n_v + sum_i c_i F_i[v]`` over the active fields only;
the fields are the rig's delta shapes, in-between residuals and corrective deltas (Lewis et al.
2014, §3.1-3.3), the coefficients ``c_i`` its weights, hat values and weight products.
Pass 2 (normals, transform feedback): area-weighted normal of each vertex's one-ring in the
deformed positions, so shading follows the deformed surface, not the neutral one.
Pass 3: lit draw of the deformed mesh under the head pose; then the marker overlay.
"""

TEX_WIDTH = 4096  # texels per row of the data textures; index i lives at (i % W, i / W)

# Pass 1. Fields in an RGBA32F texture (texel f * V + v); the active list in a uniform block,
# sized when the rig is uploaded (llvmpipe: ~10x faster than storage buffers for both).
DEFORM_VS = """
#version 430
#define N4 {n4}
#define W {width}
in vec3 in_neutral;
uniform sampler2D fields;
layout(std140) uniform Active {{ ivec4 active_idx[N4]; vec4 active_coef[N4]; }};
uniform int n_active;
uniform int n_vertices;
out vec3 out_pos;
void main() {{
    vec3 d = vec3(0.0);
    for (int i = 0; i < n_active; ++i) {{
        int t = active_idx[i >> 2][i & 3] * n_vertices + gl_VertexID;
        d += active_coef[i >> 2][i & 3] * texelFetch(fields, ivec2(t % W, t / W), 0).xyz;
    }}
    out_pos = in_neutral + d;
}}
"""

# Pass 2. Deformed positions copied (GPU side) from the feedback buffer into an RGB32F texture;
# each vertex's one-ring as (start, count) and (b, c) corner pairs in integer textures.
NORMALS_VS = """
#version 430
#define W {width}
uniform sampler2D pos;
uniform isampler2D ring_span;
uniform isampler2D ring;
out vec3 out_normal;
vec3 P(int i) {{ return texelFetch(pos, ivec2(i % W, i / W), 0).xyz; }}
void main() {{
    int v = gl_VertexID;
    vec3 a = P(v);
    ivec2 span = texelFetch(ring_span, ivec2(v % W, v / W), 0).xy;
    vec3 n = vec3(0.0);
    for (int k = span.x; k < span.x + span.y; ++k) {{
        ivec2 bc = texelFetch(ring, ivec2(k % W, k / W), 0).xy;
        n += cross(P(bc.x) - a, P(bc.y) - a);
    }}
    float l = length(n);
    out_normal = l > 0.0 ? n / l : vec3(0.0, 0.0, 1.0);
}}
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

# Blinn-Phong with a key, a fill, a sky/ground hemisphere and a rim term. Specular powers by
# repeated squaring and gamma 2.0 (sqrt): pow() is costly per pixel on a CPU rasteriser.
MESH_FS = """
#version 430
in vec3 v_world;
in vec3 v_normal;
uniform vec3 eye;
uniform vec3 albedo;
out vec4 f_color;
float pow16(float x) { x *= x; x *= x; x *= x; return x * x; }
vec3 light(vec3 n, vec3 v, vec3 dir, vec3 colour, float gloss) {
    vec3 l = normalize(dir);
    float diff = max(dot(n, l), 0.0);
    float spec = diff > 0.0 ? pow16(max(dot(n, normalize(l + v)), 0.0)) : 0.0;
    return colour * (diff * albedo + gloss * spec);
}
void main() {
    vec3 n = normalize(v_normal);
    if (!gl_FrontFacing) n = -n;  // two-sided: open meshes and either winding shade the visible side
    vec3 v = normalize(eye - v_world);
    vec3 c = albedo * mix(vec3(0.10, 0.09, 0.10), vec3(0.22, 0.22, 0.25), 0.5 + 0.5 * n.y);  // hemisphere
    c += light(n, v, vec3(-0.65, 0.50, 0.55), vec3(0.92, 0.88, 0.82), 0.12);  // key
    c += light(n, v, vec3(0.75, 0.05, 0.50), vec3(0.26, 0.30, 0.38), 0.06);   // fill
    float r = 1.0 - max(dot(n, v), 0.0);
    c += 0.25 * r * r * r * vec3(0.6, 0.7, 0.9);  // rim
    f_color = vec4(sqrt(clamp(c, 0.0, 1.0)), 1.0);
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
