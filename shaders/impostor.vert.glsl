#version 330 core
// Impostors (crowd/draw/impostors.py): an agent past the impostor distance is one quad facing the
// camera (the sun in the shadow pass, DEPTH_ONLY), drawn from the same instance record and list as its
// meshes. Its processor row starts with its key (the clip and phase of its heaviest layer): the quad
// shows that clip's two atlas frames around the phase, each from the two baked views around the
// direction it is seen from, relative to the agent's heading, at the nearest baked elevation.
in vec2 in_corner;          // the quad's corner, (0 or 1, 0 or 1): its place in a cell

uniform mat4 u_view_proj;   // camera-relative
#include "palette.glsl"
#include "vertex_packing.glsl"
#include "agent_instance.glsl"

uniform sampler2D u_impostor_clips;  // (clips, 2): row 0 (first frame, frames, loop, 0), row 1 the clip's box
uniform sampler2D u_cell_bounds;     // (columns, frames): the cell's covered rectangle (u0, v0, u1, v1), 0 to 1 of the cell
uniform int u_key_offset;   // texels from an agent's key (its first texel) to its joint 0
uniform int u_views;        // views around the up axis, at azimuth 2 pi k / u_views (k = 0 faces the agent's front)
uniform int u_elevations;
uniform float u_elevation[4];  // radians, ascending
#ifdef DEPTH_ONLY
uniform vec3 u_toward_light;  // unit, toward the sun
#else
uniform float u_focal_px;   // pixels a metre spans at a metre's depth (half the viewport's height over tan(fov / 2))
uniform float u_blend_px;   // shorter than this on screen, an impostor shows its nearest cell (crowd.draw.impostors.BLEND_PX)
#endif

flat out ivec4 v_cells;     // frame * columns + column of the 4 cells: (view 0, frame 0), (1, 0), (0, 1), (1, 1)
flat out vec2 v_blend;      // between the views, between the frames
out vec2 v_corner;
#ifndef DEPTH_ONLY
out vec3 v_world;           // camera-relative, on the quad
flat out vec3 v_toward;     // toward the camera
flat out float v_depth_range;  // metres the atlas's depth spans either side of the quad
flat out vec2 v_heading;
flat out vec4 v_tint;
flat out uint v_fade;       // lod_fade.glsl's code
#endif

void main() {
    Agent agent = instance_agent();
    vec2 heading = heading_cos_sin(agent.heading);
    float scale = agent.position_scale.w;
    vec4 key = texelFetch(u_palette0, palette_texel(agent.texel) - ivec3(u_key_offset, 0, 0), 0);
    int clip = max(int(key.x), 0);  // -1, the rest pose: the first clip's first frame
    vec4 frames = texelFetch(u_impostor_clips, ivec2(clip, 0), 0);
    vec4 box = texelFetch(u_impostor_clips, ivec2(clip, 1), 0) * scale;  // half width, bottom, height, depth half-range
    int count = int(frames.y);
    float f;
    int f0, f1;
    if (frames.z > 0.5) {  // looping: frames at phases k / count, the last blends into the first
        f = fract(key.x < 0.0 ? 0.0 : key.y) * float(count);
        f0 = min(int(f), count - 1);
        f1 = (f0 + 1) % count;
    } else {
        f = clamp(key.x < 0.0 ? 0.0 : key.y, 0.0, 1.0) * float(count - 1);
        f0 = min(int(f), max(count - 2, 0));
        f1 = min(f0 + 1, count - 1);
    }
    float frame_t = clamp(f - float(f0), 0.0, 1.0);
#ifdef DEPTH_ONLY
    vec3 toward = u_toward_light;
#else
    vec3 toward = normalize(-(agent.position_scale.xyz + vec3(0.0, box.y + 0.5 * box.z, 0.0)));
#endif
    // The direction seen from, in the agent's frame (its heading turned back).
    vec3 m = turn_about_y(vec2(heading.x, -heading.y), toward);
    float azimuth = atan(m.x, m.z) / 6.28318530718 * float(u_views);
    azimuth = azimuth < 0.0 ? azimuth + float(u_views) : azimuth;
    int v0 = int(floor(azimuth)) % u_views;
    int v1 = (v0 + 1) % u_views;
    float elevation = asin(clamp(m.y, -1.0, 1.0));
    int e = 0;
    for (int k = 1; k < u_elevations; ++k) {
        if (abs(elevation - u_elevation[k]) < abs(elevation - u_elevation[e])) e = k;
    }
    int columns = u_views * u_elevations;
    int first = int(frames.x);
    v_cells = ivec4((first + f0) * columns + e * u_views + v0, (first + f0) * columns + e * u_views + v1,
                    (first + f1) * columns + e * u_views + v0, (first + f1) * columns + e * u_views + v1);
    v_blend = vec2(fract(azimuth), frame_t);
#ifdef DEPTH_ONLY
    bool nearest = true;  // a shadow map's texel spans many of the atlas's: the nearest cell's coverage
#else
    vec4 centre = u_view_proj * vec4(agent.position_scale.xyz + vec3(0.0, box.y + 0.5 * box.z, 0.0), 1.0);
    bool nearest = box.z * u_focal_px < u_blend_px * max(centre.w, 1e-6);
#endif
    if (nearest) {  // one weight 1, three 0 (their fetches skipped), every cell that one
        v_blend = floor(v_blend + 0.5);
        v_cells = ivec4(v_cells[int(v_blend.x) + 2 * int(v_blend.y)]);
    }
    // The quad covers the covered rectangles of the cells it shows (of the clip's box, the rest is empty).
    vec4 rect = vec4(1.0, 1.0, 0.0, 0.0);
    for (int k = 0; k < 4; ++k) {
        if (k > 0 && v_cells[k] == v_cells[0]) continue;
        vec4 b = texelFetch(u_cell_bounds, ivec2(v_cells[k] % columns, v_cells[k] / columns), 0);
        rect = vec4(min(rect.xy, b.xy), max(rect.zw, b.zw));
    }
    vec2 corner = mix(rect.xy, max(rect.zw, rect.xy), in_corner);
    v_corner = corner;
    // The quad, facing `toward`, in the clip's box: x across, y up from the agent's feet.
    vec3 right = vec3(toward.z, 0.0, -toward.x);
    right = dot(right, right) > 1e-8 ? normalize(right) : vec3(1.0, 0.0, 0.0);
    vec3 up = cross(toward, right);
    vec3 world = agent.position_scale.xyz + right * ((2.0 * corner.x - 1.0) * box.x) + up * (box.y + corner.y * box.z);
#ifndef DEPTH_ONLY
    v_world = world;
    // Rasterised on a plane nearer the camera than any depth the atlas holds (with slack for the plane
    // not facing the view ray squarely), at the same place on screen: the fragment's depth is never
    // nearer than the rasterised one, so depth_greater keeps the early depth test (impostor.frag.glsl).
    float plane = max(dot(-world, toward), 1e-3);
    world *= max(plane - 1.25 * box.w - 0.05, 1e-3) / plane;
#endif
    gl_Position = u_view_proj * vec4(world, 1.0);
#ifndef DEPTH_ONLY
    v_toward = toward;
    v_depth_range = box.w;
    v_heading = heading;
    v_tint = agent.tint;
    v_fade = agent.fade;
#endif
}
