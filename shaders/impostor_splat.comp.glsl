#version 430
// The smallest impostors drawn by a compute pass instead of quads (crowd/draw/splat.py). On this path an
// impostor a few pixels tall costs the graphics pipeline a whole instance; here one invocation takes one
// and visits the pixels of its quad's screen rectangle, casting each pixel's centre onto the quad's plane,
// so a pixel gets the sample the quad's fragment shader would give it (impostor.frag.glsl, nearest cell).
// u_pass, in order (a draw at a time where a pass reads one list):
//   0 CLEAR:   the pixels and this frame's counts.
//   1 SORT:    each entry of the draw's colour list to the splat's list or the quads' list (u_region of
//              each), and each splatted pixel's nearest depth (atomicMin over its bits).
//   2 REQUEUE: the quads' list back into the draw's list, and its command's instance count.
//   3 WINNER:  among the entries at a pixel's nearest depth, the lowest agent record.
//   4 COLOUR:  that record alone writes the pixel's lit colour.
// The picture depends on no invocation order: ties go to the lowest record. impostor_resolve.frag.glsl
// draws the pixels into the frame.
layout(local_size_x = 64) in;

#include "frame.glsl"
uniform mat4 u_inverse_view_proj;  // its inverse: a pixel's ray from the camera
#include "palette.glsl"
#include "vertex_packing.glsl"
#include "agent_instance.glsl"
#include "impostor_view.glsl"
#include "impostor_sample.glsl"
#include "lighting.glsl"
#include "octahedral.glsl"

layout(std430, binding = 0) buffer Entries { uint entries[]; };    // the lists (crowd.draw.gpu_cull)
layout(std430, binding = 1) buffer Commands { uint commands[]; };  // their indirect commands, 5 words each
layout(std430, binding = 2) buffer Depths { uint splat_depth[]; };   // a pixel's nearest depth's bits; ~0: none
layout(std430, binding = 3) buffer Winners { uint splat_winner[]; };  // the lowest record at that depth
layout(std430, binding = 4) buffer Colours { uint splat_colour[]; };  // its lit colour, RGBA8
layout(std430, binding = 5) buffer Sorted { uint sorted[]; };  // per impostor draw, u_region entries: splatted, then quads
layout(std430, binding = 6) buffer Counts { uint counts[]; };  // per impostor draw: splatted, quads

uniform int u_pass;        // 0 clear, 1 sort, 2 requeue, 3 winner, 4 colour
uniform int u_command;     // this draw's command in the colour pass
uniform int u_draw;        // this draw among the impostor draws: its counts and region
uniform int u_draws;       // impostor draws
uniform int u_region;      // entries a draw's region of the sorted lists holds (the crowd's records)
uniform ivec2 u_size;      // the viewport, pixels
uniform float u_focal_px;  // pixels a metre spans at a metre's depth
uniform float u_splat_px;  // impostors shorter than this are splatted
uniform int u_max_side;    // pixels: a quad whose rectangle spans more is left to the rasteriser

// The pixels whose centres the quad's screen rectangle holds, and whether it is splatted at all.
bool splat_rect(Agent agent, inout Impostor im, out ivec2 first, out ivec2 last) {
    bool small = agent.fade == 255u && impostor_shorter(im, impostor_centre(agent, im, u_camera_view_proj), u_focal_px, u_splat_px);
    impostor_nearest(im);
    impostor_rect(im);
    vec2 lo = vec2(1e30), hi = vec2(-1e30);
    for (int k = 0; k < 4; ++k) {
        vec4 q = u_camera_view_proj * vec4(impostor_point(agent, im, mix(im.rect.xy, im.rect.zw, vec2(k & 1, k >> 1))), 1.0);
        if (q.w <= 1e-6) small = false;
        vec2 p = (q.xy / q.w * 0.5 + 0.5) * vec2(u_size);
        lo = min(lo, p);
        hi = max(hi, p);
    }
    first = max(ivec2(ceil(lo - 0.5)), ivec2(0));
    last = min(ivec2(floor(hi - 0.5)), u_size - 1);
    return small && all(lessThanEqual(last - first, ivec2(u_max_side - 1)));
}

void main() {
    // (Two-dimensional where one dimension's groups would pass GL's guaranteed 65,535: a 4K viewport's clear.)
    uint i = gl_GlobalInvocationID.y * gl_NumWorkGroups.x * gl_WorkGroupSize.x + gl_GlobalInvocationID.x;
    if (u_pass == 0) {
        if (i < uint(u_size.x * u_size.y)) {
            splat_depth[i] = 0xFFFFFFFFu;
            splat_winner[i] = 0xFFFFFFFFu;
        }
        if (i < uint(2 * u_draws)) counts[i] = 0u;
        return;
    }
    uint base = commands[5 * u_command + 4];
    uint splats = uint(2 * u_draw * u_region), quads = splats + uint(u_region);
    if (u_pass == 2) {
        if (i == 0u) commands[5 * u_command + 1] = counts[2 * u_draw + 1];
        if (i < counts[2 * u_draw + 1]) entries[base + i] = sorted[quads + i];
        return;
    }
    uint entry;
    if (u_pass == 1) {
        if (i >= commands[5 * u_command + 1]) return;
        entry = entries[base + i];
    } else {
        if (i >= counts[2 * u_draw]) return;
        entry = sorted[splats + i];
    }
    Agent agent = agent_of(entry);
    Impostor im = impostor_of(agent, false, vec3(0.0));
    ivec2 first, last;
    bool small = splat_rect(agent, im, first, last);
    if (u_pass == 1) {
        if (!small) {
            sorted[quads + atomicAdd(counts[2 * u_draw + 1], 1u)] = entry;
            return;
        }
        sorted[splats + atomicAdd(counts[2 * u_draw], 1u)] = entry;
    }
    uint record = entry & 0xFFFFFFu;
    vec3 at_agent = agent.position_scale.xyz;
    float plane = dot(at_agent, im.toward);
    for (int y = first.y; y <= last.y; ++y) {
        for (int x = first.x; x <= last.x; ++x) {
            vec2 ndc = (vec2(x, y) + 0.5) / vec2(u_size) * 2.0 - 1.0;
            vec4 far = u_inverse_view_proj * vec4(ndc, 1.0, 1.0);
            vec3 ray = far.xyz / far.w;
            float facing = dot(ray, im.toward);
            if (abs(facing) < 1e-12) continue;
            vec3 on_quad = ray * (plane / facing);
            vec3 rel = on_quad - at_agent;
            vec2 corner = vec2(dot(rel, im.right) / (2.0 * im.box.x) + 0.5, (dot(rel, im.up) - im.box.y) / im.box.z);
            if (any(lessThan(corner, im.rect.xy)) || any(greaterThan(corner, im.rect.zw))) continue;
            vec3 at = cell_coord(im.cells.x, corner);
            vec4 albedo = textureLod(u_atlas_albedo, at, 0.0);
            if (albedo.a < 0.5) continue;
            vec4 nd = textureLod(u_atlas_normal_depth, at, 0.0);
            vec3 world = atlas_surface(on_quad, im.toward, atlas_depth(nd) / albedo.a, im.box.w);
            uint depth = floatBitsToUint(window_depth(u_camera_view_proj, world));  // (>= 0: its bits order as the floats)
            int pixel = y * u_size.x + x;
            if (u_pass == 1) {
                atomicMin(splat_depth[pixel], depth);
            } else if (u_pass == 3) {
                if (splat_depth[pixel] == depth) atomicMin(splat_winner[pixel], record);
            } else if (splat_winner[pixel] == record) {
                vec3 n = turn_about_y(im.heading, oct_decode(nd.xy / albedo.a * 2.0 - 1.0));
#ifdef UNLIT
                splat_colour[pixel] = packUnorm4x8(vec4(shade_unlit(albedo.rgb / albedo.a * agent.tint.rgb, world), 1.0));
#else
                splat_colour[pixel] = packUnorm4x8(vec4(shade(albedo.rgb / albedo.a * agent.tint.rgb, world, n), 1.0));
#endif
            }
        }
    }
}
