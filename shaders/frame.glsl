// The frame's constants: one uniform block, written once a frame (crowd/draw/frame_block.py) and bound
// to one binding point, which each program reading it is told once, when it is made.
// Defines: CASCADES (the shadow cascades' count, whether or not the scene has shadows: one layout);
// FRAME_UNIFORMS: a host that sets uniforms itself and draws no shadows (the Panda3D peer,
// bench/peers_panda.py) gets the lighting alone, as plain uniforms of the same names.
#ifdef FRAME_UNIFORMS
uniform vec4 u_sun_dir;
uniform vec4 u_sun_color;
uniform vec4 u_sky_color;
uniform vec4 u_ground_color;
uniform vec4 u_fog;
#else
layout(std140) uniform Frame {
    mat4 u_camera_view_proj;            // camera-relative: the camera sits at the origin
    mat4 u_light_view_proj[CASCADES];   // each shadow cascade's, camera-relative like the positions
    vec4 u_cascade[CASCADES];           // x: metres a texel covers, y: depth bias in the tile's depth units
    vec4 u_sun_dir;                     // xyz: toward the sun, unit
    vec4 u_sun_color;
    vec4 u_sky_color;
    vec4 u_ground_color;
    vec4 u_fog;                         // rgb: colour; a: density per metre
};
#endif
