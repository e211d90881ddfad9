#version 330 core
// Impostors (crowd/draw/impostors.py): an agent past the impostor distance is one quad facing the
// camera (the sun in the shadow pass, DEPTH_ONLY), drawn from the same instance record and list as its
// meshes; impostor_view.glsl says what it shows. The smallest are splatted instead (crowd/draw/splat.py),
// which takes them out of the colour pass's list.
in vec2 in_corner;          // the quad's corner, (0 or 1, 0 or 1): its place in a cell

#ifdef DEPTH_ONLY
uniform mat4 u_view_proj;  // the shadow cascade's, camera-relative
#else
#include "frame.glsl"
#define u_view_proj u_camera_view_proj
#endif
#include "palette.glsl"
#include "vertex_packing.glsl"
#include "agent_instance.glsl"

#include "impostor_view.glsl"
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
#ifdef DEPTH_ONLY
    Impostor im = impostor_of(agent, true, u_toward_light);
    bool nearest = true;  // a shadow map's texel spans many of the atlas's: the nearest cell's coverage
#else
    Impostor im = impostor_of(agent, false, vec3(0.0));
    bool nearest = impostor_shorter(im, impostor_centre(agent, im, u_view_proj), u_focal_px, u_blend_px);
#endif
    if (nearest) impostor_nearest(im);
    impostor_rect(im);
    v_cells = im.cells;
    v_blend = im.blend;
    vec2 corner = mix(im.rect.xy, im.rect.zw, in_corner);
    v_corner = corner;
    // The quad, facing `toward`, in the clip's box: x across, y up from the agent's feet.
    vec3 world = impostor_point(agent, im, corner);
#ifndef DEPTH_ONLY
    v_world = world;
    // Rasterised on a plane nearer the camera than any depth the atlas holds (with slack for the plane
    // not facing the view ray squarely), at the same place on screen: the fragment's depth is never
    // nearer than the rasterised one, so depth_greater keeps the early depth test (impostor.frag.glsl).
    float plane = max(dot(-world, im.toward), 1e-3);
    world *= max(plane - 1.25 * im.box.w - 0.05, 1e-3) / plane;
#endif
    gl_Position = u_view_proj * vec4(world, 1.0);
#ifndef DEPTH_ONLY
    v_toward = im.toward;
    v_depth_range = im.box.w;
    v_heading = im.heading;
    v_tint = agent.tint;
    v_fade = agent.fade;
#endif
}
