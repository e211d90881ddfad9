#version 150
// The Panda3D peer's fragment shader: the crowd's own skin.frag.glsl lighting, without shadows
// (neither side of `crowd-bench peers` draws them).
#include "lighting.glsl"
in vec3 v_world;
in vec3 v_normal;
in vec4 v_color;
out vec4 p3d_FragColor;
void main() {
    vec3 n = normalize(v_normal);
    if (!gl_FrontFacing) n = -n;
    p3d_FragColor = vec4(shade(v_color.rgb, v_world, n), 1.0);
}
