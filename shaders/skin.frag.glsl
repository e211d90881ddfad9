#version 330 core
// Shared by the crowd, the weapons and the Panda3D peer of crowd-bench peers (panda_actor.vert.glsl).
#include "lighting.glsl"
in vec3 v_world;
in vec3 v_normal;
in vec4 v_color;
out vec4 o_color;
void main() {
    vec3 n = normalize(v_normal);
    if (!gl_FrontFacing) n = -n;
    o_color = vec4(shade(v_color.rgb, v_world, n), 1.0);
}
